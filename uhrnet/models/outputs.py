"""What one forward pass of any registered model returns: :func:`outputs_of` (every output, the
prediction first) and :func:`prediction_of` (the prediction). Re-exported by :mod:`uhrnet.models`."""

from __future__ import annotations

import torch

__all__ = ["outputs_of", "prediction_of"]


def outputs_of(output: torch.Tensor | tuple | list) -> tuple[torch.Tensor, ...]:
    """Every output of one forward pass as a tuple, the prediction first.

    ``output``: what ``model(x)`` returned, a ``(N, 1, H, W)`` tensor, or hNet's training-mode tuple
    ``(fused, side_1, .., side_5)`` (each ``(N, 1, H, W)``). The training loss sums over these, so deep
    supervision reaches the side outputs through this one function.
    """
    return tuple(output) if isinstance(output, (tuple, list)) else (output,)


def prediction_of(output: torch.Tensor | tuple | list) -> torch.Tensor:
    """The prediction ``(N, 1, H, W)`` of one forward pass, whatever the model (hNet: the fused output)."""
    return outputs_of(output)[0]
