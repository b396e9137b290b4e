"""What a drgan scene is, and which scene classes a config may name.

A scene turns one constellation phi_i (n x 4: x, y, z, scale in px of the real image) and the learned values of
its parameters into a differentiable image, and knows which particle every pixel shows. `Scene` is that contract;
`drgan.models.generator.Generator` relies on nothing else. drgan's scenes: `drgan.scene.scene.ParticleScene`
(secondary electrons) and `drgan.scene.transmission.TransmissionScene` (transmission).

A new imaging mode is one scene class with a ``Config`` dataclass (its ``material.imaging`` keys, ``_target_``
defaulting to the class's import path) and a ``from_config(material, render, meshes, variant)`` classmethod,
registered with `drgan.scene.config.register_scene`, plus a material config whose ``imaging._target_`` names it.
Configs (and the configs saved in checkpoints) can name registered classes only: a checkpoint's config names no
other code to run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np
    import torch

    from drgan.scene.parameters import Parameter


@runtime_checkable
class Scene(Protocol):
    """The interface of every drgan scene.

    ``spec`` holds ``parameters`` (`drgan.scene.parameters.MaterialParameters`: every scene value and the noise
    sigma), ``render`` (`drgan.scene.scene.RenderSettings`: resolution, spp, filter) and ``view_width`` (px of the
    real image the camera sees).
    """

    Config: ClassVar[type]  # the dataclass of its material.imaging keys
    n_particles: int
    spec: Any
    variant: str

    @property
    def learned(self) -> tuple[Parameter, ...]:
        """The learned scene parameters, in the order `render` takes their values (the FCN's first outputs)."""
        ...

    def set_layout(self, phi_i) -> None:
        """Pose the particles as constellation ``phi_i`` (n x 4); an all-zero row is an absent particle."""
        ...

    def render(self, values: torch.Tensor, seed: int, spp: int | None = None) -> torch.Tensor:
        """(H, W) image of the current layout, differentiable w.r.t. ``values`` (one per `learned` parameter).
        ``seed`` fixes the Monte Carlo samples (a scene without sampling noise may ignore it); ``spp`` overrides
        the configured samples per pixel."""
        ...

    def instance_labels(self) -> np.ndarray:
        """(H, W) int32 instance ids of the current layout: 0 background, k particle k."""
        ...
