"""hNet (Nguyen, Ly, Wang & Wang 2021): a U-Net with an h-shaped "global guidance" third branch.

Published in Keras; rebuilt here from the paper's description (8,632,261 parameters at 1 input / 1
output channel, the 8.63M of the UHRNet paper). With base width ``b`` (32):

* U-Net trunk: widths ``b .. 8b`` and a ``16b`` bottleneck, two 3x3 convs (bias) + LeakyReLU(0.3) per
  level, 2x2 max-pool, dropout 0.2 after the bottleneck, 3x3 stride-2 transposed convs up (no
  activation), no final 1x1 conv;
* guidance branch: at the bottleneck and after each of the 4 decoder stages, a 1x1 conv to one channel +
  LeakyReLU(0.3), then a bias-free 1->1 transposed conv with kernel ``2s`` and stride ``s`` to full size
  (``s = 16, 8, 4, 2``; the last stage is already full size). The transposed convs start as bilinear
  interpolation (trainable; Keras' default would be a random Glorot kernel);
* outputs: five side outputs (a 1x1 conv on each guidance map) and the fused output (a 1x1 conv over
  the five guidance maps concatenated), which is the prediction.

In training mode ``forward`` returns ``(fused, side_1, .., side_5)`` (side 1 from the bottleneck, side 5
from the full-resolution stage), all ``(N, out_channels, H, W)``, to be trained with a loss on every
output; in eval mode it returns the fused tensor only.
"""

from __future__ import annotations

from functools import partial

import torch
from torch import nn

from uhrnet.models.blocks import Decoder, DoubleConv, Encoder, activation, upsample_conv, widths_for

NEGATIVE_SLOPE = 0.3


def bilinear_kernel_(weight: torch.Tensor, factor: int) -> torch.Tensor:
    """Fill a ``(C, C, 2f, 2f)`` transposed-conv weight with bilinear upsampling by ``factor`` (in place)."""
    k = weight.shape[-1]
    centre = (k - 1) / 2
    taps = 1 - torch.abs(torch.arange(k, dtype=torch.float64) - centre) / factor
    kernel = torch.outer(taps, taps).to(weight.dtype)
    with torch.no_grad():
        weight.zero_()
        for c in range(min(weight.shape[0], weight.shape[1])):
            weight[c, c] = kernel
    return weight


class GuidanceBranch(nn.Sequential):
    """``1x1 conv -> 1 channel -> LeakyReLU(0.3) [-> ConvTranspose(k=2s, stride s, no bias)]``."""

    def __init__(self, in_channels: int, scale: int) -> None:
        layers: list[nn.Module] = [nn.Conv2d(in_channels, 1, 1), activation(NEGATIVE_SLOPE)]
        if scale > 1:
            up = upsample_conv(1, 1, scale, kernel_size=2 * scale, bias=False)
            bilinear_kernel_(up.weight, scale)
            up.keep_init = True  # uhrnet.models.init leaves the bilinear kernel alone
            layers.append(up)
        super().__init__(*layers)


class HNet(nn.Module):
    """hNet; see the module docstring for the outputs in training and eval mode."""

    PARTS = {"encoder": ("encoder", "bottleneck"), "decoder": ("decoder", "guidance", "side_heads", "fuse")}
    """Child modules of each part, for ``uhrnet train --freeze`` (:mod:`uhrnet.models.freeze`)."""

    def __init__(
        self, in_channels: int = 1, out_channels: int = 1, base_channels: int = 32, dropout: float = 0.2
    ) -> None:
        super().__init__()
        self.config = {
            "name": "hnet",
            "in_channels": in_channels,
            "out_channels": out_channels,
            "base_channels": base_channels,
            "dropout": dropout,
        }
        widths = widths_for(base_channels)
        block = partial(DoubleConv, negative_slope=NEGATIVE_SLOPE)
        self.encoder = Encoder(in_channels, widths[:-1], block)
        self.bottleneck = block(widths[-2], widths[-1])
        self.dropout = nn.Dropout(dropout)
        self.decoder = Decoder(widths, block, partial(upsample_conv, factor=2, kernel_size=3))
        scales = [2**i for i in range(len(widths) - 1, -1, -1)]  # 16, 8, 4, 2, 1
        self.guidance = nn.ModuleList(GuidanceBranch(w, s) for w, s in zip(widths[::-1], scales))
        n = len(self.guidance)
        self.side_heads = nn.Conv2d(n, n * out_channels, 1, groups=n)  # one 1x1 conv per guidance map
        self.fuse = nn.Conv2d(n, out_channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, ...]:
        x, skips = self.encoder(x)
        x = self.dropout(self.bottleneck(x))
        features = [x, *self.decoder(x, skips)]
        maps = torch.cat([branch(f) for branch, f in zip(self.guidance, features)], dim=1)
        fused = self.fuse(maps)
        if not self.training:
            return fused
        return (fused, *self.side_heads(maps).chunk(len(self.guidance), dim=1))
