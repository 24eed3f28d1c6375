"""Running a trained model on images of any size (shared by evaluate and predict)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def pad_to_multiple(x: torch.Tensor, multiple: int = 16) -> tuple[torch.Tensor, tuple[int, int]]:
    """Pad ``(N, C, H, W)`` at the bottom/right (edge replication) to multiples of ``multiple``."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x, (h, w)


@torch.no_grad()
def predict_labels(model: torch.nn.Module, fringe: torch.Tensor, size: tuple[int, int] | None = None,
                   amp: bool = False) -> torch.Tensor:
    """Labels ``(N, 1, H, W)`` for fringes ``(N, 1, H, W)`` in [-1, 1], at the input's own size.

    ``size``: run the network at this (H, W) (the ``--resize`` a model was trained with) and resample
    the prediction back. Inputs whose sides are not multiples of 16 are padded and cropped back.
    """
    model.eval()
    device = next(model.parameters()).device
    x = fringe.to(device, torch.float32)
    h, w = x.shape[-2:]
    if size is not None and tuple(size) != (h, w):
        x = F.interpolate(x, size=tuple(size), mode="area")
    x, (hh, ww) = pad_to_multiple(x)
    ctx = torch.autocast(device.type, dtype=torch.float16 if device.type == "cuda" else torch.bfloat16) \
        if amp else torch.autocast(device.type, enabled=False)
    with ctx:
        out = model(x)
    out = (out[0] if isinstance(out, (tuple, list)) else out).float()[..., :hh, :ww]
    if out.shape[-2:] != (h, w):
        out = F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False)
    return out
