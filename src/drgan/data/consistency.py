"""Does the data fit the material? Checked on a few training images before any patch is mined or rendered.

A material is made for one kind of image: its polarity (particles brighter or darker than the background)
and its particle size (``material.particle_size_px``) are part of it. Training a bright-particle material on
transmission images, or a 40 px material on 200 px particles, runs for hours and learns nothing useful, so
``drgan.train`` stops first and names both sides and the override (``data.check_material=false``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from drgan.core.errors import ConfigError, DataError
from drgan.data.classical import SegmentParams, resolve_params, segment_diameters, segment_particles
from drgan.scene.config import Material

log = logging.getLogger(__name__)

SIZE_FACTOR = 2.0  # data and material particle sizes may differ by up to this factor
N_IMAGES = 6  # training images looked at (about one second each)


def data_particle_size(
    images: Sequence[np.ndarray], polarity: str, segment: SegmentParams | None = None
) -> float | None:
    """Median equivalent diameter (px) of the particles segmented in ``images`` (one particle scale for all), or None
    when none is found."""
    try:
        segment, _ = resolve_params(list(images), segment, polarity)
    except DataError:
        return None
    diameters = np.concatenate(
        [segment_diameters(segment_particles(image, segment, polarity)[0], segment) for image in images]
        or [np.zeros(0)]
    )
    return float(np.median(diameters)) if diameters.size else None


def check_material_fits_data(material: Material, polarity: str, size_px: float | None, data_dir) -> dict:
    """Refuse (ConfigError) a material whose polarity or particle size contradicts the data; return the comparison.

    ``material.particle_size_px`` is a particle's largest extent, ``size_px`` the data's median equivalent
    diameter (~0.9 x the largest extent for the TiO2 particles); SIZE_FACTOR leaves room for both that and the
    classical segmentation's error (on the TiO2 train images it gives 21.5 px SEM, 29.3 px TSEM; masks: 26.5)."""
    name, expected = material.name, material.polarity
    report = {
        "material": name,
        "material_polarity": expected,
        "data_polarity": polarity,
        "material_particle_size_px": material.particle_size_px,
        "data_particle_size_px": size_px,
    }
    override = "data.check_material=false runs it anyway"
    if polarity != expected:
        raise ConfigError(
            f"material={name} is made for {expected} particles ({material.made_for or 'its images'}), but the "
            f"particles in data.dir={data_dir} are {polarity}er than their background. Choose a material for {polarity} "
            f"particles (e.g. material=tio2_tsem for transmission images), or profile your images to get one: python -m "
            f"drgan.profile data.dir={data_dir} name=my_particles. If the detection is wrong, set data.polarity; "
            f"{override}"
        )
    size = material.particle_size_px
    if size_px is not None:
        ratio = size_px / float(size)
        report["size_ratio"] = ratio
        if not 1.0 / SIZE_FACTOR <= ratio <= SIZE_FACTOR:
            raise ConfigError(
                f"material={name} has particles of {float(size):g} px (material.particle_size_px), but the particles in "
                f"data.dir={data_dir} measure {size_px:.1f} px (median equivalent diameter of a classical segmentation), "
                f"{ratio:.2f}x as large. Set material.particle_size_px (and data.segment sizes) for your images, or "
                f"profile them: python -m drgan.profile data.dir={data_dir} name=my_particles; {override}"
            )
    log.info("data fits material %s: %s", name, report)
    return report
