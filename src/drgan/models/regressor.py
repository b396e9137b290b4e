"""The FCN that maps one constellation phi_i to the material's learned parameters.

Input: the flattened n x 4 constellation, normalised by the view width so that positions lie in about
[-0.5, 0.5] and sizes in (0, 1) whatever the pixel scale. Output: one value in (0, 1) per learned
parameter (sigmoid), rescaled by the caller into that parameter's limits.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn.utils.parametrizations import weight_norm


class ParameterRegressor(nn.Module):
    """Four blocks of Dropout -> weight-normed Linear(hidden) -> ReLU, then weight-normed Linear -> Sigmoid."""

    def __init__(self, n_particles: int, n_outputs: int, hidden: int = 128, blocks: int = 4, dropout: float = 0.1):
        super().__init__()
        layers: list[nn.Module] = []
        width = 4 * n_particles
        for _ in range(blocks):
            layers += [nn.Dropout(dropout), weight_norm(nn.Linear(width, hidden)), nn.ReLU()]
            width = hidden
        layers += [weight_norm(nn.Linear(width, n_outputs)), nn.Sigmoid()]
        self.net = nn.Sequential(*layers)
        self.n_particles = n_particles
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Xavier initialisation (as in the paper) of the direction of every weight-normed layer."""
        for module in self.net:
            if isinstance(module, nn.Linear):
                direction = module.parametrizations.weight.original1
                nn.init.xavier_uniform_(direction)
                with torch.no_grad():
                    module.parametrizations.weight.original0.copy_(direction.norm(dim=1, keepdim=True))
                nn.init.zeros_(module.bias)

    def forward(self, phi_normalised: torch.Tensor) -> torch.Tensor:
        """(B, n, 4) -> (B, n_outputs) in (0, 1)."""
        return self.net(phi_normalised.flatten(start_dim=1))
