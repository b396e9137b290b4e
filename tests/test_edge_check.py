"""The generated-against-real edge check: the profile's edge measurement recovers a known blur."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from drgan.data.particle_edge import crossing
from drgan.synthetic.edge_check import compare, edge_of


def blurred_discs(sigma: float, n: int = 12, size: int = 96, radius: float = 11.0):
    """n images of one bright disc (grey 0.8 on 0.2) blurred by a Gaussian of ``sigma`` px, with its pixel-centre mask."""
    images, labels = [], []
    for k in range(n):
        centre = size / 2 + 0.37 * k % 1.0  # sub-pixel positions differ
        fine = 4  # the disc drawn at 4 x and area-averaged: a continuous edge
        yy, xx = (np.mgrid[: size * fine, : size * fine] + 0.5) / fine
        disc = ((yy - centre) ** 2 + (xx - centre) ** 2 <= radius**2).astype(float)
        disc = disc.reshape(size, fine, size, fine).mean(axis=(1, 3))
        images.append(0.2 + 0.6 * ndi.gaussian_filter(disc, sigma))
        y, x = np.mgrid[:size, :size] + 0.5
        labels.append(((y - centre) ** 2 + (x - centre) ** 2 <= radius**2).astype(np.int32))
    return images, labels


def test_crossing_interpolates_between_bins():
    assert crossing([-1, 0, 1, 2], [1.0, 0.8, 0.4, 0.0], 0.5) == pytest.approx(0.75)
    assert np.isnan(crossing([0, 1], [1.0, 0.9], 0.5))


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_the_edge_profile_recovers_a_known_blur_and_puts_half_contrast_on_the_true_edge(sigma):
    images, labels = blurred_discs(sigma)
    ramp = edge_of(images, lambda k: labels[k], lambda k: labels[k] > 0)
    assert ramp["particles"] == 12
    # a Gaussian-blurred straight edge rises from 10 to 90 % over 2 x 1.2816 sigma (the disc's curvature adds little)
    assert ramp["width_px"] == pytest.approx(2.5631 * sigma, rel=0.15)
    assert abs(ramp["half_px"]) < 0.35  # a symmetric blur keeps half contrast on the edge


def test_a_wider_rendered_blur_is_reported_as_a_wider_ramp():
    sharp, wide = blurred_discs(1.0), blurred_discs(2.0)
    real = edge_of(sharp[0], lambda k: sharp[1][k], lambda k: sharp[1][k] > 0)
    generated = edge_of(wide[0], lambda k: wide[1][k], lambda k: wide[1][k] > 0)
    assert compare(real, generated)["width_ratio"] == pytest.approx(2.0, rel=0.2)


def rendered_spheres(filter_stddev: float, n: int = 12):
    """n renders (96 px, spp 4) of one lit sphere (18 px across) on a black stage, blurred by the render's Gaussian
    reconstruction filter of ``filter_stddev`` px, with their exact labels."""
    import torch
    from conftest import make_scene

    from drgan.scene.scene import TopLight

    particle = {"base_color": {"value": 1.0}, "roughness": {"value": 1.0}}
    scene = make_scene(
        resolution=96, spp=4, n=1, particle=particle, stage=None, filter_stddev=filter_stddev, torus_light=None,
        top_light=TopLight(radiance=1.0, size=2.0), view_width=96.0,
    )  # fmt: skip
    images, labels = [], []
    for k in range(n):
        scene.set_layout(np.array([[0.3 * k - 1.5, 0.2 * k - 1.0, 10, 18]], dtype=np.float32))
        images.append(np.clip(scene.render(torch.zeros(0), seed=k).numpy().astype(np.float64), 0, None))
        labels.append(scene.instance_labels().astype(np.int32))
    return images, labels


def test_the_edge_check_recovers_the_blur_of_rendered_edges():
    sharp, soft = rendered_spheres(0.5), rendered_spheres(2.0)
    ramps = [edge_of(imgs, lambda k, lab=lab: lab[k], lambda k, lab=lab: lab[k] > 0) for imgs, lab in (sharp, soft)]
    assert all(r is not None and r["particles"] == 12 for r in ramps)
    # the shaded sphere darkens towards its rim (its own ramp, ~3.5 px at a 0.5 px filter); a 2 px filter widens it to
    # at least the filter's own 10-90 % width (2 x 1.2816 x 2 = 5.1 px) and never to more than the two in quadrature
    assert ramps[1]["width_px"] > ramps[0]["width_px"] + 1.0
    assert 0.9 * 2.5631 * 2.0 <= ramps[1]["width_px"] <= 1.05 * np.hypot(2.5631 * 2.0, ramps[0]["width_px"])


def test_the_outline_moves_to_half_contrast_only_when_the_crossing_is_a_ramp():
    from types import SimpleNamespace

    from drgan.data.particle_edge import MAX_OUTLINE_SHIFT_PX, outline_shift

    assert outline_shift(None) == 0.0  # no mean edge: sizes stay at the segmented outline
    assert outline_shift(SimpleNamespace(half_contrast_px=float("nan"))) == 0.0
    assert outline_shift(SimpleNamespace(half_contrast_px=-0.93)) == -0.93
    assert outline_shift(SimpleNamespace(half_contrast_px=MAX_OUTLINE_SHIFT_PX + 0.5)) == 0.0  # a halo, not a ramp
