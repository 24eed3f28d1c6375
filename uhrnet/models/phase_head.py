"""Physics head: any registered architecture predicts the fringe phase, and the rig turns it into height.

The backbone (``unet``, ``uhrnet``, ``hnet``, the ablations) is built with three output channels:

* channel 0, the *coarse height* ``c`` in the height head's units (height above the reference plane in
  cm, i.e. mm / 10: :class:`uhrnet.checkpoint.LabelHead` maps it to labels exactly as for the height head);
* channels 1, 2: ``(cos, sin)`` of the wrapped projector phase ``phi_w`` the pixel sees, in fppsim's
  ``phase_true`` convention (rad, :mod:`fppsim.geometry.rig`); their length ``r`` is the network's confidence.

Height follows through the calibrated rig (:class:`uhrnet.physics.rig_layer.RigLayer`, a fixed, differentiable
phase <-> height layer equal to fppsim's triangulation)::

    Phi_c = phase_from_height(10 c)                              coarse height's absolute phase, rad
    o     = arg sum r exp(i (phi_w - Phi_c))                     one phase offset per image (detached)
    k     = round((Phi_c - phi_w + o) / 2 pi)                    fringe order from the coarse height
    h     = height_from_phase(phi_w - o + 2 pi k)                height, mm

so the phase fixes height to a fraction of a millimetre wherever the coarse height is within half a
fringe period (about 3.6 mm on the figshare rig). The per-image offset ``o`` absorbs a real projector's
unknown pattern phase (a constant the synthetic data cannot teach); on fppsim's own data it is ~0.
Where the phase is not trusted (``r < min_confidence``) the coarse height is kept. ``round`` has no
gradient: training supervises the phase (``1 - cos`` against ``phase_true``) and the coarse height
(the run's height loss), and the final height where its order is right (:class:`uhrnet.training.losses.PhaseHeadLoss`).

``forward(x)`` returns the final height in the height head's units ``(N, 1, H, W)``, so prediction,
evaluation, export and benchmarks treat both heads alike; :meth:`PhaseHead.parts` returns every
intermediate for training. The rig travels in ``config["rig"]`` (fppsim's rig dictionary), so
``build_model(**config)`` rebuilds the head from a checkpoint. Images must have the rig camera's size.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from uhrnet.physics.rig_layer import RigLayer, circular_mean

from uhrnet.models.outputs import outputs_of
from uhrnet.errors import InputError

__all__ = ["PhaseHead", "PHASE_CHANNELS"]

PHASE_CHANNELS = 3  # coarse height, cos, sin

TWO_PI = 2.0 * math.pi


class PhaseHead(nn.Module):
    """Wraps a 3-channel backbone; see the module docstring.

    Parameters
    ----------
    backbone : nn.Module with ``out_channels == 3`` and a ``config`` dict (from the registry).
    rig : fppsim rig dictionary (:meth:`fppsim.geometry.rig.Rig.to_dict`) whose camera matches the images.
    min_confidence : phase confidence ``r`` below which the coarse height is kept.
    """

    def __init__(self, backbone: nn.Module, rig: dict, min_confidence: float = 0.3) -> None:
        super().__init__()
        if backbone.config.get("out_channels") != PHASE_CHANNELS:
            raise InputError(f"the phase head needs a backbone with {PHASE_CHANNELS} outputs, "
                             f"got {backbone.config.get('out_channels')}")
        self.backbone = backbone
        rig = rig.to_dict() if hasattr(rig, "to_dict") else dict(rig)
        self.layer = RigLayer.from_dict(rig)
        self.min_confidence = float(min_confidence)
        self.config = {**backbone.config, "head": "phase", "rig": rig, "min_confidence": self.min_confidence}
        self.last_parts: list[dict] = []

    def _combine(self, out: torch.Tensor) -> dict:
        coarse = out[:, :1].float()
        cos, sin = out[:, 1:2].float(), out[:, 2:3].float()
        conf = torch.sqrt(cos * cos + sin * sin)
        wrapped = torch.atan2(sin, cos)
        coarse_mm = 10.0 * coarse
        phi_c = self.layer.phase_from_height(coarse_mm)
        with torch.no_grad():  # one constant per image: the pattern phase a real projector may add
            d = wrapped - phi_c
            w = conf.clamp(max=1.0)
            offset = circular_mean(d, w)
            order = torch.round((phi_c - wrapped + offset) / TWO_PI)
        phase = wrapped - offset + TWO_PI * order
        height_mm = self.layer.height_from_phase(phase)
        trusted = conf >= self.min_confidence
        height_mm = torch.where(trusted & torch.isfinite(height_mm), height_mm, coarse_mm)
        return {"coarse": coarse, "cos_sin": (cos, sin), "wrapped": wrapped, "confidence": conf, "offset": offset,
                "order": order, "phase": phase, "height": height_mm / 10.0}

    def parts(self, x: torch.Tensor) -> list[dict]:
        """Every intermediate (module docstring) for each backbone output (hNet trains several)."""
        cam = self.layer.grid_shape
        if tuple(x.shape[-2:]) != tuple(cam):
            raise InputError(f"the phase head's rig sees {cam[1]}x{cam[0]} px images; got {x.shape[-1]}x{x.shape[-2]}")
        return [self._combine(o) for o in outputs_of(self.backbone(x))]

    def forward(self, x: torch.Tensor):
        """The height (height head units), one per backbone output in training mode (hNet: a tuple);
        the intermediates stay in :attr:`last_parts` for the training loss."""
        parts = self.parts(x)
        self.last_parts = parts if self.training else []
        heights = tuple(p["height"] for p in parts)
        return heights if len(heights) > 1 else heights[0]
