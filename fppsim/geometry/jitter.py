"""Seeded per-sample rig jitter: the projector's yaw and focal length vary a little around the rig's.

A network trained on one exact carrier (one fringe period map) learns it as a constant and fails on a
real rig whose period differs by a few per cent (the held-out real frames of the figshare rig measure
11.4-11.6 px where the published sample measures 11.5-12.0 px). Jittering the projector makes the
carrier a variable the network has to read from the image.

Why these two parameters: scaling the projector focal length scales the fringe period but leaves the
lateral fringe shift per millimetre of height (in camera pixels) unchanged, so the height cue stays
exact; a small yaw changes the left-to-right period trend. The baseline is not jittered because it
changes the height sensitivity without a visible cue.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace as dc_replace

import numpy as np

from fppsim.geometry.rig import Device, Rig, rotation
from fppsim.errors import InputError

__all__ = ["RigJitter", "jitter_rig"]


@dataclass(frozen=True)
class RigJitter:
    """Uniform jitter ranges: yaw in radians (+-), focal length as a relative change (+-).

    ``RigJitter(0, 0)`` leaves the rig untouched. The defaults spread the default rig's mid-image
    period (11.72 px) over about 11.4-12.1 px and its left/right half difference over 0.3-0.65 px.
    """

    yaw: float = 0.02
    focal: float = 0.03

    def __post_init__(self):
        if not (0 <= self.yaw < 0.5 and 0 <= self.focal < 0.5):
            raise InputError(f"rig jitter must satisfy 0 <= yaw < 0.5 rad and 0 <= focal < 0.5, got {self}")

    @property
    def enabled(self) -> bool:
        return self.yaw > 0 or self.focal > 0

    def to_dict(self) -> dict:
        return asdict(self)


def jitter_rig(rig: Rig, rng: np.random.Generator, jitter: RigJitter) -> Rig:
    """A copy of ``rig`` whose projector is turned by ``U(-yaw, yaw)`` about its own y axis and whose
    focal lengths are scaled by ``1 + U(-focal, focal)``; the principal point moves so the world
    origin still lands on the same projector pixel (the scene stays centred in the pattern).

    Always draws two numbers from ``rng`` (also when disabled) so streams stay aligned.
    """
    d_yaw, d_focal = rng.uniform(-1.0, 1.0, 2)
    if not jitter.enabled:
        return rig
    p = rig.projector
    origin_px = p.project(np.zeros(3), distort=False)[0]
    R = rotation("y", d_yaw * jitter.yaw) @ p.R
    t = -R @ p.center
    K = p.K.copy()
    K[0, 0] *= 1.0 + d_focal * jitter.focal
    K[1, 1] *= 1.0 + d_focal * jitter.focal
    x = t / t[2]  # the world origin in the new projector frame, normalised
    K[0, 2] = origin_px[0] - K[0, 0] * x[0] - K[0, 1] * x[1]
    K[1, 2] = origin_px[1] - K[1, 1] * x[1]
    proj = Device(K=K, R=R, t=t, width=p.width, height=p.height, dist=p.dist)
    return dc_replace(rig, projector=proj)
