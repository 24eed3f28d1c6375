"""The classic U-Net (Ronneberger et al. 2015) for height regression, the paper's U-Net baseline.

Widths ``b, 2b, 4b, 8b`` plus a ``16b`` bottleneck (``b = 64``: 31,030,593 parameters at 1 input / 1
output channel; ``b = 32`` is ablation Model A, 7,759,521 = the paper's 7.76M). Two 3x3 convs with bias
and ReLU per level, no normalisation, 2x2 max-pool down, 2x2 stride-2 transposed conv up, final 1x1 conv
without activation. Padding keeps sizes, so ``H x W -> H x W`` for H, W multiples of 16.
"""

from __future__ import annotations

from functools import partial

import torch
from torch import nn

from uhrnet.models.blocks import Decoder, DoubleConv, Encoder, upsample_conv, widths_for


class UNet(nn.Module):
    """``forward(x: (N, in_channels, H, W)) -> (N, out_channels, H, W)``."""

    PARTS = {"encoder": ("encoder", "bottleneck"), "decoder": ("decoder", "head")}
    """Child modules of each part, for ``uhrnet train --freeze`` (:mod:`uhrnet.models.freeze`)."""

    def __init__(self, in_channels: int = 1, out_channels: int = 1, base_channels: int = 64) -> None:
        super().__init__()
        self.config = {
            "name": "unet",
            "in_channels": in_channels,
            "out_channels": out_channels,
            "base_channels": base_channels,
        }
        widths = widths_for(base_channels)
        self.encoder = Encoder(in_channels, widths[:-1], DoubleConv)
        self.bottleneck = DoubleConv(widths[-2], widths[-1])
        self.decoder = Decoder(widths, DoubleConv, partial(upsample_conv, factor=2, kernel_size=2))
        self.head = nn.Conv2d(widths[0], out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x, skips = self.encoder(x)
        return self.head(self.decoder(self.bottleneck(x), skips)[-1])
