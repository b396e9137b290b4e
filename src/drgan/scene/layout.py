"""Particle layouts: the transformation tensor Phi of shape (m, n, 4).

Phi holds m constellations of n particles; each row is (x, y, z, scale).

Units and frame (shared with the scene builder):
- One scene unit is one pixel of the real image at native resolution (the 256 x 256 real patch).
- The camera looks straight down (-z) at the stage plane z = 0; the view is the square
  x, y in [-W/2, W/2], W = view width in px (256 by default).
- ``scale`` is the particle's largest extent in px (meshes have unit largest extent), i.e. its diameter.
- ``z`` is the height of the particle centre above the stage: a particle resting on the stage has
  z = scale / 2, and no particle ever has z < scale / 2 (it would sink into the stage).

A layout is sampled in two steps: a size distribution draws every scale, then a placement draws the
positions given those scales: the size distributions are in drgan.scene.sizes, the placements in
drgan.scene.placements. Everything here is numpy only, so it runs before any renderer is loaded.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from drgan.core import targets
from drgan.core.errors import ConfigError, check_int_at_least, check_positive
from drgan.scene.placements import OfficialPlacement, Placement, PoissonAgglomerates, Random2D, Random3D
from drgan.scene.sizes import BimodalSize, LognormalSize, NormalSize, SizeDistribution

__all__ = ["sample_layouts", "particle_counts", "size_from_config", "placement_from_config"]


# ----------------------------------------------------------------------------------------------------------------
# The transformation tensor.


PLACEMENT_REDRAWS = 50  # sizes drawn again for a constellation that does not fit, before the error stands


def sample_layouts(
    m: int,
    n: int,
    size: SizeDistribution,
    placement: Placement,
    view_width: float = 256.0,
    seed: int = 0,
    n_min: int | None = None,
) -> np.ndarray:
    """Phi: float32 (m, n, 4) of m constellations of n particles, rows (x, y, z, scale) in px.

    ``n_min``: when given, constellation i shows k_i particles, drawn uniformly from n_min..n; its first
    k_i rows are placed together and the other n - k_i rows are all zero: absent particles, which the scene
    does not render (real patches show anywhere from a few to dozens of particles; one fixed count gives
    every synthetic image the same density). The same arguments and seed give the same Phi (numpy
    default_rng(seed)); ``n_min`` = None consumes the generator exactly as before it existed. A constellation whose
    sizes cannot be placed (the placement's ConfigError) draws its sizes again, up to PLACEMENT_REDRAWS times; a
    draw that fits the first time consumes the generator as before.
    """
    check_int_at_least("sample_layouts", "m", m, 1)
    check_int_at_least("sample_layouts", "n", n, 1)
    check_positive("sample_layouts", "view_width", view_width)
    if n_min is not None:
        check_int_at_least("sample_layouts", "n_min", n_min, 1)
        if n_min > n:
            raise ConfigError(f"sample_layouts: n_min = {n_min} must be <= n = {n} (the most particles a scene holds)")
    if not isinstance(size, (NormalSize, LognormalSize, BimodalSize)):
        raise ConfigError(f"sample_layouts: size must be NormalSize, LognormalSize or BimodalSize, got {size!r}")
    if not isinstance(placement, (Random2D, Random3D, PoissonAgglomerates, OfficialPlacement)):
        raise ConfigError(
            f"sample_layouts: placement must be Random2D, Random3D, PoissonAgglomerates or OfficialPlacement, "
            f"got {placement!r}"
        )
    rng = np.random.default_rng(seed)
    sizes = size.sample(rng, (m, n))
    counts = np.full(m, n) if n_min is None else rng.integers(n_min, n + 1, size=m)
    layouts = np.zeros((m, n, 4), dtype=np.float32)
    for i, k in enumerate(counts):
        drawn = sizes[i, :k]
        for redraw in range(PLACEMENT_REDRAWS + 1):
            try:
                layouts[i, :k, :3] = placement.sample(rng, drawn, float(view_width))
                break
            except ConfigError as error:
                # A draw of sizes that does not fit the view (a few large particles of a wide distribution in a
                # full view): draw the constellation's sizes again, as a real window would hold other particles.
                if redraw == PLACEMENT_REDRAWS:
                    raise ConfigError(f"{error} (constellation {i}: {PLACEMENT_REDRAWS + 1} draws of sizes)") from None
                drawn = size.sample(rng, (k,))
        layouts[i, :k, 3] = drawn
    return layouts


def particle_counts(layouts: np.ndarray) -> np.ndarray:
    """Particles present in each constellation of Phi (m, n, 4): rows with a scale > 0."""
    return (np.asarray(layouts)[..., 3] > 0).sum(axis=-1)


# ----------------------------------------------------------------------------------------------------------------
# Construction from Hydra config groups (conf/gan/size/*.yaml, conf/gan/placement/*.yaml).

_SIZE_KINDS: dict[str, type] = {"normal": NormalSize, "lognormal": LognormalSize, "bimodal": BimodalSize}
_PLACEMENT_KINDS: dict[str, type] = {
    "random_2d": Random2D,
    "random_3d": Random3D,
    "poisson": PoissonAgglomerates,
    "official": OfficialPlacement,
}


# The size distributions and placements were classes of this module until they moved to drgan.scene.sizes and
# drgan.scene.placements; checkpoints saved before that name them here in their config's size._target_ and
# placement._target_, which reads as the class's path now (the same class, so such a checkpoint still loads).
MOVED_TARGETS: dict[str, str] = {
    f"drgan.scene.layout.{cls.__name__}": targets.target_path(cls)
    for cls in (*_SIZE_KINDS.values(), *_PLACEMENT_KINDS.values())
}


def _from_config(group: str, kinds: dict[str, type], cfg: Mapping) -> object:
    """The object a ``group`` config names: ``_target_``, the import path of one of ``kinds`` (an allow-list: a
    config, e.g. one saved in a checkpoint, names no other code to run; a path from before a class moved reads as
    its path now, `MOVED_TARGETS`), plus the dataclass's fields."""
    if isinstance(cfg, Mapping) and cfg.get("_target_") in MOVED_TARGETS:
        cfg = {**cfg, "_target_": MOVED_TARGETS[cfg["_target_"]]}
    return targets.build(cfg, kinds.values(), group)


def size_from_config(cfg: Mapping) -> SizeDistribution:
    """Size distribution from a mapping: _target_ (NormalSize | LognormalSize | BimodalSize here) plus the
    dataclass fields."""
    return _from_config("size", _SIZE_KINDS, cfg)  # type: ignore[return-value]


def placement_from_config(cfg: Mapping) -> Placement:
    """Placement from a mapping: _target_ (Random2D | Random3D | PoissonAgglomerates | OfficialPlacement) plus the
    fields."""
    return _from_config("placement", _PLACEMENT_KINDS, cfg)  # type: ignore[return-value]
