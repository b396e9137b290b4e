"""drgan.synthetic.noise_check: fine-scale noise by class on hand-made images and the comparison by hand
(generate's noise_check.json on a tiny run: tests/test_generate.py)."""

from __future__ import annotations

import numpy as np
import pytest

from drgan.synthetic import noise_check as nc


def _disc_image(sigma_background: float, sigma_particle: float, seed: int = 0, size: int = 96):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    particle = np.hypot(yy - size / 2, xx - size / 2) <= size / 4
    image = np.where(particle, 0.7, 0.2) + rng.normal(0, 1, (size, size)) * np.where(
        particle, sigma_particle, sigma_background
    )
    return image, particle


def test_fine_noise_reads_each_class_alone_and_scales_with_the_noise():
    image, particle = _disc_image(0.01, 0.04)
    background, core = nc.fine_noise(image, particle)
    # white noise through "image minus its 1 px blur" keeps one fixed share of its std: the same in both classes
    assert core / background == pytest.approx(4.0, rel=0.1)
    twice, _ = _disc_image(0.02, 0.04)
    assert nc.fine_noise(twice, particle)[0] / background == pytest.approx(2.0, rel=0.1)
    # the outline's step (0.5 grey) would dominate both if the margin did not keep it out
    clean = np.where(particle, 0.7, 0.2)
    assert max(nc.fine_noise(clean, particle)) < 1e-3  # a tenth of the weakest noise measured above
    assert nc.fine_noise(clean, particle, margin=0)[0] > 0.01
    # a class with too few pixels is not measured
    assert np.isnan(nc.fine_noise(image, np.zeros_like(particle))[1])


def test_compare_takes_each_sides_median_and_the_ratio_by_hand():
    generated = [(0.02, 0.06), (0.04, float("nan")), (0.03, 0.10)]
    real = [(0.01, 0.02), (0.01, 0.04), (0.02, 0.03)]
    out = nc.compare(generated, real)
    assert out["background"] == {"real": 0.01, "generated": 0.03, "ratio": 3.0}
    assert out["particles"] == {"real": 0.03, "generated": 0.08, "ratio": pytest.approx(2.667, abs=1e-3)}
    assert nc.off_by(out) == [
        "background 3 x as noisy as the real train patches",
        "particles 2.7 x as noisy as the real train patches",
    ]
    calm = nc.compare([(0.011, 0.02)], [(0.01, 0.02)])
    assert nc.off_by(calm) == [] and "background 1.1 x" in nc.summary_line(calm)
    assert nc.compare([(0.01, float("nan"))], [(0.01, 0.02)])["particles"]["ratio"] is None
