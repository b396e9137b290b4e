"""A small U-Net: grey image (N, 1, H, W) in [0, 1] -> class logits (N, n_classes, H, W).

`depth` levels (depth - 1 poolings), `base` filters at the top level, doubling per level. Each level is
two 3x3 conv + BatchNorm + ReLU; upsampling is a 2x2 transposed convolution, skips are concatenated.
Inputs whose sides are not multiples of 2**(depth - 1) are reflect-padded and the output cropped back.
Its receptive field (`receptive_field`) grows with the depth; ``depth: auto`` (`auto_depth`) takes the depth whose field
spans the pairs' particles.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from drgan.core.errors import ConfigError

# the depths `auto_depth` chooses from (both measured: experiments/statistics/closed_loop.md, "Large particles")
AUTO_DEPTHS = (4, 5)
FIELD_PER_DIAMETER = 1.25  # `auto_depth`: the receptive field spans this many median particle diameters


def receptive_field(depth: int) -> int:
    """The side (px) of the input square every output pixel sees, for depth >= 3: two 3x3 convolutions per level,
    2 x 2 pooling and up-sampling between levels (44, 92, 188 px at depth 3, 4, 5; pixels off the poolings' grid see
    up to 8 % more)."""
    if depth < 3:
        raise ValueError(f"receptive_field: depth >= 3, got {depth}")
    return 12 * 2 ** (depth - 1) - 4


def auto_depth(diameter_px: float | None) -> tuple[int, str]:
    """(depth, why) for ``model.depth: auto``: the smallest of AUTO_DEPTHS whose receptive field spans
    FIELD_PER_DIAMETER x the pairs' area-weighted median particle diameter (at the working scale), else the largest.
    A particle much wider than the field has an inside that sees no edge: the network can only tell it from the
    background by its grey, which the training's brightness, contrast and texture jitter make unreliable."""
    low, high = AUTO_DEPTHS
    if diameter_px is None or not diameter_px > 0:
        return low, f"auto: {low}, no particle measured in the pairs"
    for depth in range(low, high + 1):
        if receptive_field(depth) >= FIELD_PER_DIAMETER * diameter_px:
            break
    return depth, (
        f"auto: {depth}, receptive field {receptive_field(depth)} px for particles of {diameter_px:.0f} px (area-weighted "
        f"median; at least {FIELD_PER_DIAMETER:g} x wanted, at most depth {high})"
    )


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    def __init__(self, in_channels: int = 1, n_classes: int = 3, depth: int = 4, base: int = 16):
        super().__init__()
        if depth < 1 or base < 1 or n_classes < 2 or in_channels < 1:
            raise ConfigError(
                f"UNet: need depth >= 1, base >= 1, n_classes >= 2, in_channels >= 1; got {depth=}, {base=}, {n_classes=}, {in_channels=}"
            )
        widths = [base * 2**i for i in range(depth)]
        self.depth, self.n_classes = depth, n_classes
        self.down = nn.ModuleList([_block(in_channels if i == 0 else widths[i - 1], w) for i, w in enumerate(widths)])
        self.upsample = nn.ModuleList(
            [nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2) for i in range(depth - 1)]
        )
        self.up = nn.ModuleList([_block(2 * widths[i], widths[i]) for i in range(depth - 1)])
        self.head = nn.Conv2d(widths[0], n_classes, 1)

    @property
    def multiple(self) -> int:
        """Input sides are padded to a multiple of this."""
        return 2 ** (self.depth - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        m = self.multiple
        pad_h, pad_w = (-h) % m, (-w) % m
        if pad_h or pad_w:
            mode = "reflect" if pad_h < h and pad_w < w else "replicate"
            x = F.pad(x, (0, pad_w, 0, pad_h), mode=mode)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        for i in reversed(range(self.depth - 1)):
            x = self.up[i](torch.cat([skips[i], self.upsample[i](x)], dim=1))
        return self.head(x)[..., :h, :w]
