"""Exponential moving average of a network's weights (Polyak averaging), as ``uhrnet train --ema``.

After optimizer step ``n`` (1-based), every floating-point parameter and buffer ``w`` of the network
updates its average ``a``:

    d_n = min(decay, (1 + n) / (10 + n))
    a  <- d_n * a + (1 - d_n) * w

The ramp ``(1 + n) / (10 + n)`` lets the average forget the random initial weights within the first
few dozen steps; afterwards it spans about ``1 / (1 - decay)`` steps. Integer buffers (batch-norm step
counters) are copied. The average lives in a copy of the network, so evaluating it costs nothing extra.
"""

from __future__ import annotations

import copy

import torch
from uhrnet.errors import InputError

__all__ = ["WeightEMA"]


class WeightEMA:
    """Moving average of ``net``'s parameters and buffers; ``module`` is the averaged network."""

    def __init__(self, net: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise InputError(f"decay must be in (0, 1), got {decay}")
        self.decay = float(decay)
        self.updates = 0
        self.module = copy.deepcopy(net).eval()
        for p in self.module.parameters():
            p.requires_grad_(False)
        self._pairs = self._pair(net)

    def _pair(self, net: torch.nn.Module):
        src, dst = net.state_dict(keep_vars=True), self.module.state_dict(keep_vars=True)
        if src.keys() != dst.keys():
            raise InputError("the network's parameters differ from the average's")
        floats = [(dst[k], src[k]) for k in src if src[k].is_floating_point()]
        others = [(dst[k], src[k]) for k in src if not src[k].is_floating_point()]
        return floats, others

    @torch.no_grad()
    def update(self) -> float:
        """Fold the network's current weights into the average; returns the decay used."""
        self.updates += 1
        d = min(self.decay, (1.0 + self.updates) / (10.0 + self.updates))
        floats, others = self._pairs
        if floats:
            avg = [a.data for a, _ in floats]
            cur = [w.data for _, w in floats]
            torch._foreach_lerp_(avg, cur, 1.0 - d)
        for a, w in others:
            a.data.copy_(w.data)
        return d

    def state_dict(self) -> dict:
        return self.module.state_dict()

    def load_state_dict(self, state: dict, updates: int) -> None:
        self.module.load_state_dict(state)
        self.updates = int(updates)
