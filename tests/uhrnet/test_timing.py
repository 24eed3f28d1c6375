"""uhrnet.scoring.timing: timing and memory helpers."""

from __future__ import annotations

import torch

from uhrnet.scoring.timing import inference_seconds, peak_memory_bytes, time_call


def test_timing_and_memory_helpers():
    model = torch.nn.Conv2d(1, 2, 3, padding=1).train()
    seconds = inference_seconds(model, (1, 1, 16, 16), "cpu", warmup=1, repeats=3)
    assert seconds > 0 and model.training
    calls = []
    assert len(time_call(lambda: calls.append(1), "cpu", warmup=2, repeats=3)) == 3 and len(calls) == 5
    peak = peak_memory_bytes(lambda: torch.ones(64, 2**20).sum(), "cpu")  # a 256 MiB temporary
    assert peak is None or peak >= 200 * 2**20
