"""The edge fringe of transmission images (material.imaging.fringe): the scene's term (a Laplacian-of-Gaussian ring
of the darkening, learned amplitude, exact gradients, off without a fringe) and the profile's measurement of it
(drgan.data.particle_edge's mean particle edge). Tiny renders and synthetic discs only."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import TEST_VARIANT, TINY_PHI, compose
from test_transmission import _finite_difference

from drgan.core.errors import ConfigError

LIMITS = {
    "background": {"min": 0.3, "max": 1.0},
    "absorption": {"min": 0.001, "max": 0.5},
    "floor": {"min": 0.0, "max": 0.5},
}
VIEW = 64.0


def make_scene(fringe=None, n=4, resolution=16, spp=4, meshes=None, transmission=None):
    """A transmission scene; ``fringe`` (amplitude spec, width in px of the real image) or None."""
    from drgan.scene import particle_meshes as procedural
    from drgan.scene.config import TransmissionImaging
    from drgan.scene.scene import RenderSettings
    from drgan.scene.transmission import TransmissionScene, TransmissionSpec

    limits = LIMITS if transmission is None else transmission
    imaging = TransmissionImaging(**limits, fringe=fringe)
    spec = TransmissionSpec(
        imaging.material_parameters({"min": 0.001, "max": 0.2}),
        RenderSettings(resolution=resolution, spp=spp),
        VIEW,
        fringe_width_px=None if fringe is None else fringe["width_px"],
    )
    return TransmissionScene(meshes or [procedural.sphere(2)], n, spec, variant=TEST_VARIANT)


# -- the term -------------------------------------------------------------------------------------
@pytest.mark.parametrize("width, tolerance", [(0.7, 0.3), (1.5, 0.06), (3.0, 0.03)])
def test_edge_fringe_of_a_straight_step_peaks_at_one_w_outside(width, tolerance):
    """Outside a straight step (1 inside, 0 outside) the term is s phi(s / w) / (w phi(1)): +1 at s = w, -1 at
    s = -w; the sampled kernel keeps that within a few % from 1.5 px (a ring narrower than a pixel is only its
    first pixel), is antisymmetric about the edge and sums to 0 on a constant map."""
    from drgan.scene.transmission import edge_fringe

    step = torch.zeros(64, 64, dtype=torch.float64)
    step[:, :32] = 1.0  # the edge at x = 32; pixel j's centre lies at s = j + 0.5 - 32
    row = edge_fringe(step, width)[32].numpy()
    s = np.arange(64) + 0.5 - 32
    expected = s * np.exp(-0.5 * (s / width) ** 2) / (width * math.exp(-0.5))
    np.testing.assert_allclose(row, expected, atol=tolerance)
    np.testing.assert_allclose(row[32:], -row[:32][::-1], atol=1e-12)  # antisymmetric: the edge stays put
    assert abs(row.sum()) < 1e-9
    np.testing.assert_allclose(
        edge_fringe(torch.full((16, 16), 0.7, dtype=torch.float64), width).numpy(), 0, atol=1e-12
    )


def test_fringe_amplitude_is_a_learned_parameter_in_the_fcn_order():
    scene = make_scene({"amplitude": {"min": -0.2, "max": 0.4}, "width_px": 4.0})
    assert [p.key for p in scene.learned] == [
        "transmission.background",
        "transmission.absorption",
        "transmission.floor",
        "transmission.fringe_amplitude",
    ]
    assert scene.spec.fringe_width_render_px == pytest.approx(1.0)  # 4 px of the real image, 16 px over a 64 px view
    fixed = make_scene({"amplitude": {"value": 0.1}, "width_px": 4.0})
    assert [p.name for p in fixed.learned] == ["background", "absorption", "floor"]
    assert [p.key for p in make_scene().learned] == [p.key for p in fixed.learned]


@pytest.mark.parametrize("amplitude", [0.25, -0.15])
def test_gradients_with_a_fringe_match_finite_differences(amplitude):
    """A non-linear loss of the rendered image: autograd's gradient w.r.t. every learned value, the fringe's
    amplitude included, against central differences (the render has no Monte Carlo noise: exact agreement)."""
    scene = make_scene({"amplitude": {"min": -0.5, "max": 0.5}, "width_px": 6.0}, spp=4)
    scene.set_layout(TINY_PHI)
    rng = np.random.default_rng(5)
    target = torch.from_numpy(rng.uniform(0.2, 0.9, size=(16, 16)))
    weights = torch.from_numpy(rng.normal(size=(16, 16)))

    def loss(values):
        image = scene.render(values, seed=0)
        return ((image - target) ** 2).sum() + (weights * torch.exp(image)).sum()

    values = torch.tensor([0.8, 0.12, 0.15, amplitude], dtype=torch.float64, requires_grad=True)
    loss(values).backward()
    expected = _finite_difference(loss, values.detach())
    assert (expected.abs() > 1e-3).all(), expected  # the fringe's amplitude matters to this loss
    torch.testing.assert_close(values.grad, expected, rtol=1e-6, atol=1e-8)


def test_without_a_fringe_renders_are_identical():
    """No fringe: no term and no parameter, the image exactly the one without the feature (the formula through the
    reconstruction blur, bit for bit); a fringe fixed at amplitude 0 renders the same bits too."""
    from drgan.scene.scene import reconstruction_blur

    plain = make_scene()
    plain.set_layout(TINY_PHI)
    values = torch.tensor([0.8, 0.12, 0.15])
    image = plain.render(values, seed=0)
    t = plain.thickness()
    transmitted = torch.ones(16 * 16).index_put(
        (torch.nonzero((t > 0).any(dim=1)).squeeze(1),), torch.exp(-values[1] * t[(t > 0).any(dim=1)]).mean(dim=1)
    )
    expected = reconstruction_blur(values[2] + (values[0] - values[2]) * transmitted.reshape(16, 16), 0.5)
    torch.testing.assert_close(image, expected, rtol=0, atol=0)
    off = make_scene({"amplitude": {"value": 0.0}, "width_px": 6.0})
    off.set_layout(TINY_PHI)
    torch.testing.assert_close(off.render(values, seed=0), image, rtol=0, atol=0)
    on = make_scene({"amplitude": {"value": 0.2}, "width_px": 6.0})
    on.set_layout(TINY_PHI)
    assert not torch.equal(on.render(values, seed=0), image)


@pytest.mark.parametrize("amplitude", [0.3, -0.3])
def test_a_fringe_renders_a_ring_of_its_sign_outside_the_edge_and_labels_stay(amplitude):
    """One opaque disc-like particle: a positive amplitude brightens a ring just outside the edge above the bare
    film (and darkens the particle's rim), a negative one darkens it; the labels are those without a fringe."""
    from drgan.data.particle_edge import signed_distance

    size, background = 32, 0.7
    phi = np.array([[0.0, 0.0, 0.0, 32.0]], np.float32)  # a sphere of 32 px on a 64 px view: 16 render px across
    spec = {"amplitude": {"min": -0.5, "max": 0.5}, "width_px": 2.0}  # 1 render px (32 px over a 64 px view)
    values = torch.tensor([background, 0.5, 0.05])
    plain, ring = make_scene(n=1, resolution=size), make_scene(spec, n=1, resolution=size)
    plain.set_layout(phi)
    ring.set_layout(phi)
    without = plain.render(values, seed=0).numpy()
    with_ring = ring.render(torch.cat([values, torch.tensor([amplitude])]), seed=0).numpy()
    labels = ring.instance_labels()
    np.testing.assert_array_equal(labels, plain.instance_labels())
    d = signed_distance(labels > 0)
    outside, rim = (d > 0) & (d < 2.5), (d < 0) & (d > -2.5)
    assert (without[outside] <= background + 1e-6).all()  # no ring without the term
    change_out = with_ring[outside].mean() - without[outside].mean()
    change_rim = with_ring[rim].mean() - without[rim].mean()
    assert np.sign(change_out) == np.sign(amplitude) and abs(change_out) > 0.02
    assert np.sign(change_rim) == -np.sign(amplitude)
    if amplitude > 0:
        assert with_ring[outside].max() > background + 0.05  # a bright ring, brighter than the film
    far = d > 8  # the kernel's reach (4 w), the blur's, and the coverage of pixels beside the labels
    np.testing.assert_allclose(with_ring[far], without[far], atol=1e-4)  # the ring stays near the edge


# -- configuration --------------------------------------------------------------------------------
def _material(fringe):
    return {
        "name": "tem",
        "n_particles": 4,
        "particle_size_px": 10,
        "view_width": int(VIEW),
        "noise_sigma": {"min": 0.001, "max": 0.2},
        "imaging": {"_target_": "drgan.scene.transmission.TransmissionScene", **LIMITS, "fringe": fringe},
    }


@pytest.mark.parametrize(
    "fringe, message",
    [
        ({"amplitude": {"min": 0.0, "max": 0.3}, "width_px": -1.0}, r"material.imaging.fringe.width_px=-1.0"),
        ({"amplitude": {"min": 0.0, "max": 0.3}, "width_px": 0}, r"material.imaging.fringe.width_px=0"),
        ({"amplitude": {"min": 0.3, "max": 0.1}, "width_px": 1.5}, r"material.imaging.fringe.amplitude: min=0.3 > max"),
        ({"amplitude": {"min": 0.0, "max": 0.3}}, r"material.imaging.fringe.width_px: missing"),
        ({"width_px": 1.5}, r"material.imaging.fringe.amplitude: missing"),
        ({"amplitude": {"max": 0.3}, "width_px": 1.5}, r"material.imaging.fringe.amplitude: expected keys"),
        ({"amplitude": {"value": 0.1}, "width_px": 1.5, "sigma": 2}, r"material.imaging.fringe.sigma: unknown key"),
        ({"amplitude": {"value": 0.1}, "width_px": "wide"}, r"material.imaging.fringe.width_px='wide'"),
        (0.3, r"material.imaging.fringe=0.3"),
    ],
)
def test_bad_fringe_settings_are_config_errors_naming_the_key(fringe, message):
    from drgan.models import build

    with pytest.raises(ConfigError, match=message):
        build.scene_spec(_material(fringe), {"resolution": 16, "spp": 1})


def test_a_signed_amplitude_is_accepted_and_no_fringe_is_the_default():
    from drgan.models import build

    spec = build.scene_spec(_material({"amplitude": {"min": -0.3, "max": 0.0}, "width_px": 1.5}), {})
    assert spec.fringe_width_px == 1.5 and spec.parameters.learned[3].low == -0.3
    assert build.scene_spec(_material(None), {}).fringe_width_px is None
    cfg = compose(["material=tio2_tsem"], config_name="render")
    assert cfg.material.imaging.fringe is None  # the shipped material renders none


def test_a_fringe_from_the_command_line_trains_through_the_generator(one_torch_thread):
    from drgan.models import build

    cfg = compose(
        [
            "material=tio2_tsem",
            "material.imaging.fringe={amplitude: {min: 0.0, max: 0.4}, width_px: 6.0}",
            "renderer.resolution=16",
            "material.view_width=64",
            "material.particle_size_px=12",
            "renderer.spp=4",
            f"renderer.variant={TEST_VARIANT}",
            "material.n_particles=4",
            "material.n_particles_min=2",
            "material.meshes.count=2",
        ],
        config_name="train",
    )
    generator = build.build_generator(cfg)
    assert generator.learned[3].key == "transmission.fringe_amplitude"
    images, values = generator.render_batch(torch.as_tensor(build.sample_phi(cfg, 1, seed=0)))
    assert values.shape == (1, 5) and 0.0 <= float(values[0, 3].detach()) <= 0.4
    (images * torch.linspace(-1, 1, 16)).sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in generator.regressor.parameters())


# -- the measurement ------------------------------------------------------------------------------
def disc_coverage(rng, size=256, n=12, radius=(8.0, 14.0), sub=4) -> np.ndarray:
    """(size, size) coverage of non-overlapping discs, well apart (supersampled by ``sub``)."""
    yy, xx = (np.mgrid[: size * sub, : size * sub] + 0.5) / sub
    coverage = np.zeros((size * sub, size * sub))
    placed = []
    for _ in range(n):
        r = rng.uniform(*radius)
        for _ in range(200):
            c = rng.uniform(r + 20, size - r - 20, 2)
            if all(np.hypot(*(c - c2)) > r + r2 + 30 for c2, r2 in placed):
                placed.append((c, r))
                coverage[(yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r] = 1.0
                break
    return coverage.reshape(size, sub, size, sub).mean(axis=(1, 3))


def disc_image(rng, scene_fringe=None, ring=None, background=0.8, contrast=0.5, noise=0.02, blur=0.5):
    """Dark discs on a bright film: the scene's fringe term (amplitude, width) on the darkening before the blur,
    or a drawn Gaussian ring (height in particle contrast, > 0 brighter than the film; distance; stddev 1 px)."""
    from drgan.data.particle_edge import signed_distance
    from drgan.scene.scene import reconstruction_blur
    from drgan.scene.transmission import edge_fringe

    coverage = disc_coverage(rng)
    darkening = torch.from_numpy(contrast * coverage)
    image = background - darkening
    if scene_fringe is not None:
        image = image + scene_fringe[0] * edge_fringe(darkening, scene_fringe[1])
    image = reconstruction_blur(image, blur).numpy()
    if ring is not None:
        d = signed_distance(coverage > 0.5)
        image = image + ring[0] * contrast * np.exp(-0.5 * (d - ring[1]) ** 2) * (d > 0)
    return np.clip(image + noise * rng.standard_normal(image.shape), 0, 1).astype(np.float32)


def measure_edge(images):
    """The mean edge profile of ``images`` (dark discs, 16-28 px), segmented at 24 px, the scale the search finds on
    the discs with drawn rings: the edge is measured here; the scale search, with a fringe too, is the profile
    test's (below) and test_particles'."""
    from drgan.data import particle_edge
    from drgan.data.annotations import annotation_mask
    from drgan.data.classical import SegmentParams, resolve_params
    from drgan.data.measurements import segment_image

    params, _ = resolve_params(images, SegmentParams(scale=24.0), "dark")
    samples = []
    for image in images:
        labels, foreground = segment_image(image, params, "dark")[:2]
        samples.append(particle_edge.edge_samples(image, labels, foreground, annotation_mask(image)))
    return particle_edge.edge_profile(samples)


def test_no_fringe_reads_as_none():
    edge = measure_edge([disc_image(np.random.default_rng(0)) for _ in range(2)])
    assert edge.particles >= 20 and edge.contrast == pytest.approx(-0.5, abs=0.05)
    assert edge.ring.kind == "none" and edge.fringe is None and not edge.fringe_detected
    np.testing.assert_allclose(edge.profile[edge.distance_px > 3], 0, atol=0.01)
    np.testing.assert_allclose(edge.profile[edge.distance_px < -3], 1, atol=0.05)


@pytest.mark.parametrize("height, distance", [(0.1, 3.0), (0.05, 2.0), (-0.1, 4.0)])
def test_a_drawn_ring_is_measured_with_its_height_and_distance(height, distance):
    """A Gaussian ring of known height (particle contrast) and distance outside each disc: the profile's ring has
    them back (10 % of the height, half a pixel), of the right kind: brighter than the film around dark discs is
    an overshoot (opposite grey), darker a bump (like the particles)."""
    rng = np.random.default_rng(1)
    edge = measure_edge([disc_image(rng, ring=(height, distance)) for _ in range(2)])
    assert edge.ring.kind == ("opposite" if height > 0 else "like")
    assert edge.ring.height == pytest.approx(height, rel=0.1)
    assert edge.ring.distance_px == pytest.approx(distance, abs=0.5)
    assert abs(edge.ring.height) >= 3 * edge.ring.height_se


@pytest.mark.parametrize("amplitude, width", [(0.2, 1.5), (0.3, 2.5), (-0.3, 2.5)])
def test_the_scenes_own_fringe_is_fitted_back(amplitude, width):
    """Discs through the scene's fringe term and blur: the fitted fringe has the amplitude (15 %) and width (20 %)
    the images were made with, so a material written from it renders the ring it saw."""
    rng = np.random.default_rng(2)
    edge = measure_edge([disc_image(rng, scene_fringe=(amplitude, width)) for _ in range(2)])
    assert edge.fringe_detected and edge.fringe is not None
    assert edge.fringe.amplitude == pytest.approx(amplitude, rel=0.15)
    assert edge.fringe.width_px == pytest.approx(width, rel=0.2)


def test_the_profile_writes_a_measured_fringe_into_a_transmission_material(tmp_path, monkeypatch):
    """drgan.profile on dark discs with the scene's fringe: the material (parent tio2_tsem) gets
    material.imaging.fringe, its amplitude learned from 0 to twice the fit, and composes into a scene with it; the
    report and its figure show the edge profile."""
    from PIL import Image

    from drgan.models import build
    from drgan.profile import ProfileSettings, profile
    from drgan.profiling.proposal import FRINGE_LIMIT_FACTOR

    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for i in range(2):
        image = disc_image(rng, scene_fringe=(0.2, 1.5))
        Image.fromarray((image * 255).round().astype(np.uint8)).save(folder / f"im{i}.png")
    monkeypatch.chdir(tmp_path)
    result = profile(
        ProfileSettings.from_config(
            compose([f"data.dir={folder}", "name=tem_discs", f"out={tmp_path / 'out'}"], config_name="profile")
        )
    )
    assert result.material.parent == "tio2_tsem"
    edge = result.edge
    assert edge["ring"]["kind"] == "opposite" and edge["fringe"]["amplitude"] == pytest.approx(0.2, rel=0.2)
    written = result.material.fringe
    assert written["amplitude"]["min"] == 0.0
    assert written["amplitude"]["max"] == pytest.approx(FRINGE_LIMIT_FACTOR * edge["fringe"]["amplitude"], abs=1e-3)
    assert written["width_px"] == pytest.approx(1.5, rel=0.25)
    text = (tmp_path / "drgan_conf" / "material" / "tem_discs.yaml").read_text()
    assert "imaging.fringe: a ring opposite to the particles' grey" in text
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Mean particle edge" in report and "written: `material.imaging.fringe" in report
    assert (tmp_path / "out" / "edge_profile.png").stat().st_size > 0
    cfg = compose(["material=tem_discs"], config_name="train")
    assert cfg.material.imaging.fringe.width_px == written["width_px"]
    spec = build.scene_spec(cfg.material, {"resolution": 16, "spp": 1})
    assert spec.fringe_width_px == written["width_px"]
    assert spec.parameters.learned[3].key == "transmission.fringe_amplitude"
