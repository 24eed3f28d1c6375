"""The heads a model can end in, registered like the architectures (``build_model(name, head=...)``).

A head says what it needs and gives, so the trainer, the options' checks and prediction ask the
registry instead of testing for a head's name:

- ``height`` (the papers' networks): the architecture's own one-channel output is the height.
- ``phase`` (:class:`uhrnet.models.phase_head.PhaseHead`): the backbone predicts a coarse height and the
  fringe phase (cosine, sine); a calibrated rig turns them into height. It needs the rig, learns the phase
  from synthetic samples' ``phase_true``, and sees whole camera images (each pixel is a ray of the rig).
  Its training loss wraps the run's loss (:data:`uhrnet.training.losses.HEAD_LOSSES`).

Adding a head: a module in ``uhrnet/models/`` with the ``nn.Module`` that wraps a backbone, one
:class:`Head` entry below, and its loss in ``HEAD_LOSSES`` when it trains on more than the height.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import nn

from uhrnet.models.phase_head import PHASE_CHANNELS, PhaseHead

__all__ = ["Head", "HEADS"]


@dataclass(frozen=True)
class Head:
    """One registered head.

    name : the ``--head`` value. backbone_channels : output channels the backbone is built with (None:
    the architecture's own). needs_rig : a calibrated rig (fppsim rig dictionary) turns its outputs into
    height, and travels in the model's config. phase_targets : training batches carry the true phase
    (synthetic samples only). whole_images : no ``--crop`` / ``--resize`` (each pixel is a camera ray).
    wrap : ``(backbone, rig, **options) -> nn.Module`` around the registry's backbone; None: the backbone
    is the model.
    """

    name: str
    backbone_channels: int | None = None
    needs_rig: bool = False
    phase_targets: bool = False
    whole_images: bool = False
    wrap: Callable[..., nn.Module] | None = None


HEADS: dict[str, Head] = {
    "height": Head("height"),
    "phase": Head("phase", backbone_channels=PHASE_CHANNELS, needs_rig=True, phase_targets=True, whole_images=True,
                  wrap=PhaseHead),
}
