"""How an exported model is checked against the checkpoint it came from (ONNX, TorchScript and the
reference code's weights alike): the seeded check input and the pass rule

    passed  <=>  max |exported - checkpoint|  <=  CHECK_RTOL * max(max - min of the checkpoint's output, 1e-6)
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["CHECK_RTOL", "check_input", "compare_outputs"]

CHECK_RTOL = 1e-4


def check_input(in_channels: int, height: int, width: int, seed: int = 0) -> torch.Tensor:
    """The seeded check input: ``(1, in_channels, height, width)`` float32 uniform in [-1, 1]."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand((1, in_channels, height, width), generator=g) * 2 - 1


def compare_outputs(got: np.ndarray, want: np.ndarray, rtol: float = CHECK_RTOL) -> dict:
    """``{"max_abs_diff", "output_range", "tolerance", "passed"}`` of an exported output ``got`` against the
    checkpoint's ``want`` (same shape; compared in float64)."""
    diff = float(np.max(np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))))
    span = float(np.ptp(want))
    tol = rtol * max(span, 1e-6)
    return {"max_abs_diff": diff, "output_range": span, "tolerance": tol, "passed": bool(diff <= tol)}
