"""The 3-layer PatchGAN discriminator of pix2pix (NLayerDiscriminator, n_layers=3), for one grey channel.

(B, 1, H, W) images in [0, 1] -> (B, 1, H', W') logits, one per overlapping 70 x 70 px receptive field:
D judges local texture, which is what the learned BSDF parameters and noise can change.
"""

from __future__ import annotations

from torch import nn

from drgan.core.errors import ConfigError


class PatchDiscriminator(nn.Module):
    """Conv(4, s2) -> LeakyReLU, then (n_layers - 1) x [Conv(4, s2) -> BatchNorm -> LeakyReLU],
    Conv(4, s1) -> BatchNorm -> LeakyReLU, Conv(4, s1) -> 1 logit map. Filters 64, 128, 256, 512."""

    def __init__(self, in_channels: int = 1, filters: int = 64, n_layers: int = 3, slope: float = 0.2):
        super().__init__()
        self.n_layers = n_layers
        layers: list[nn.Module] = [nn.Conv2d(in_channels, filters, 4, 2, 1), nn.LeakyReLU(slope, True)]
        mult = 1
        for n in range(1, n_layers):
            prev, mult = mult, min(2**n, 8)
            layers += [
                nn.Conv2d(filters * prev, filters * mult, 4, 2, 1, bias=False),  # BatchNorm carries the bias
                nn.BatchNorm2d(filters * mult),
                nn.LeakyReLU(slope, True),
            ]
        prev, mult = mult, min(2**n_layers, 8)
        layers += [
            nn.Conv2d(filters * prev, filters * mult, 4, 1, 1, bias=False),
            nn.BatchNorm2d(filters * mult),
            nn.LeakyReLU(slope, True),
            nn.Conv2d(filters * mult, 1, 4, 1, 1),
        ]
        self.net = nn.Sequential(*layers)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Xavier (Glorot) initialisation of the convolutions, as in the paper; BatchNorm at (1, 0)."""
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)

    def min_size(self) -> int:
        """Smallest input side: each stride-2 conv halves it, and the two last 4 x 4 convs need >= 3 px."""
        return 3 * 2**self.n_layers

    def check_size(self, size: int) -> None:
        if size < self.min_size():
            raise ConfigError(
                f"discriminator: images of {size} px are too small for a {self.n_layers}-layer PatchGAN "
                f"(expected >= {self.min_size()} px; raise renderer.resolution and data.patch_size)"
            )

    def forward(self, image):
        return self.net(image)
