"""The heads a model can end in, registered like the architectures (``build_model(name, head=...)``).

A head says what it needs and gives, so the trainer, ``build_model``, the options' checks and prediction ask
the registry instead of testing for a head's name (``tests/test_layers.py`` fails on a head's name in the
trainer or in ``build_model``):

- ``height`` (the papers' networks): the architecture's own one-channel output is the height.
- ``phase`` (:class:`uhrnet.models.phase_head.PhaseHead`): the backbone predicts a coarse height and the
  fringe phase (cosine, sine); a calibrated rig turns them into height. It needs the rig, learns the phase
  from synthetic samples' ``phase_true``, and sees whole camera images (each pixel is a ray of the rig).
  Its option ``min_confidence`` goes to the wrapper; its training loss (``"phase_head"`` in
  :data:`uhrnet.training.losses.HEAD_LOSSES`) wraps the run's loss.

Adding a head: a module in ``uhrnet/models/`` with the ``nn.Module`` that wraps a backbone (its
``config`` holds ``head`` and its options, so ``build_model(**config)`` rebuilds it), one :class:`Head`
entry below, and its loss registered in ``HEAD_LOSSES`` when it trains on more than the height.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import nn

from uhrnet.models.phase_head import PHASE_CHANNELS, PhaseHead

__all__ = ["Head", "HEADS", "DEFAULT_HEAD"]


@dataclass(frozen=True)
class Head:
    """One registered head.

    name : the ``--head`` value. backbone_channels : output channels the backbone is built with (None:
    the architecture's own). needs_rig : a calibrated rig (fppsim rig dictionary) turns its outputs into
    height, and travels in the model's config. phase_targets : training batches carry the true phase
    (synthetic samples only). whole_images : no ``--crop`` / ``--resize`` (each pixel is a camera ray).
    wrap : ``(backbone, rig, **options) -> nn.Module`` around the registry's backbone; None: the backbone
    is the model. options : the keyword options of ``build_model`` that belong to the head and go to
    ``wrap`` (e.g. ``min_confidence``), not to the backbone. loss : the name of its training loss in
    :data:`uhrnet.training.losses.HEAD_LOSSES` (it wraps the run's ``--loss``); None: the run's loss
    supervises the model's outputs.
    """

    name: str
    backbone_channels: int | None = None
    needs_rig: bool = False
    phase_targets: bool = False
    whole_images: bool = False
    wrap: Callable[..., nn.Module] | None = None
    options: tuple[str, ...] = ()
    loss: str | None = None


HEADS: dict[str, Head] = {
    "height": Head("height"),
    "phase": Head("phase", backbone_channels=PHASE_CHANNELS, needs_rig=True, phase_targets=True, whole_images=True,
                  wrap=PhaseHead, options=("min_confidence",), loss="phase_head"),
}

DEFAULT_HEAD = "height"  # a model built without a head, and every checkpoint made before heads existed
