"""The transmission scene (dark particles on a bright film): path lengths against geometry, exact gradients,
labels, configuration, and the spatially correlated noise (material.noise_grain_px). Tiny renders only."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from conftest import TEST_VARIANT, compose

from drgan.core.errors import ConfigError

LIMITS = {
    "background": {"min": 0.3, "max": 1.0},
    "absorption": {"min": 0.001, "max": 0.5},
    "floor": {"min": 0.0, "max": 0.5},
}
SIGMA = {"min": 0.001, "max": 0.2}
VIEW = 64.0


def transmission_parameters(limits, sigma=SIGMA):
    from drgan.scene.config import ParameterRange, TransmissionImaging
    from drgan.scene.parameters import MaterialParameters, noise_parameter

    imaging = TransmissionImaging(**{key: ParameterRange(**spec) for key, spec in limits.items()})
    return MaterialParameters(imaging.scene_parameters(), noise_parameter(ParameterRange(**sigma)))


def make_scene(meshes=None, n=4, resolution=16, spp=4, transmission=None, filter_stddev=0.5):
    from drgan.scene import particle_meshes as procedural
    from drgan.scene.scene import RenderSettings
    from drgan.scene.transmission import TransmissionScene, TransmissionSpec

    params = transmission_parameters(LIMITS if transmission is None else transmission)
    spec = TransmissionSpec(params, RenderSettings(resolution=resolution, spp=spp, filter_stddev=filter_stddev), VIEW)
    return TransmissionScene(meshes or [procedural.sphere(2)], n, spec, variant=TEST_VARIANT)


def pixel_centres(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """World x, y (px of the real image) of each render pixel's centre: x right, y up, row 0 at the top."""
    c = (np.arange(resolution) + 0.5) / resolution * VIEW - VIEW / 2
    return np.meshgrid(c, -c, indexing="xy")


def unit_cube() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 1.0, 1.0))


@pytest.fixture(scope="module")
def tiny():
    from conftest import TINY_PHI

    scene = make_scene()
    scene.set_layout(TINY_PHI)
    return scene


# -- path lengths ---------------------------------------------------------------------------------
def test_sphere_path_length_is_its_chord():
    """Seen from above, a sphere of radius r has path length 2 sqrt(r^2 - d^2) at distance d from its centre.
    The icosphere lies between its inscribed sphere (radius of the nearest face plane) and its vertices' sphere,
    so every chord lies between the two spheres' chords."""
    from drgan.scene import particle_meshes

    mesh, scale, size = particle_meshes.sphere(3), 40.0, 32
    scene = make_scene([mesh], n=1, resolution=size, spp=1)
    scene.set_layout(np.array([[0.0, 0.0, 0.0, scale]], np.float32))
    t = scene.thickness().reshape(size, size).numpy()
    outer = np.linalg.norm(mesh.vertices, axis=1).max() * scale
    inner = np.abs(np.einsum("fk,fk->f", mesh.face_normals, mesh.triangles[:, 0])).min() * scale
    x, y = pixel_centres(size)
    d = np.hypot(x, y)
    chord = lambda r: 2.0 * np.sqrt(np.clip(r * r - d * d, 0.0, None))  # noqa: E731
    assert outer - inner < 0.01 * outer  # the test would prove little on a coarse sphere
    assert (t >= chord(inner) - 1e-3 * outer).all() and (t <= chord(outer) + 1e-3 * outer).all()
    centre = d < 0.8 * inner
    assert np.abs(t[centre] - chord(outer)[centre]).max() < 0.02 * outer
    assert (t[d > outer + 1.0] == 0).all()


def test_cube_path_length_is_its_side_and_overlaps_add():
    side, size = 24.0, 16
    scene = make_scene([unit_cube()], n=2, resolution=size, spp=4)
    x, y = pixel_centres(size)
    inside = (np.abs(x) < side / 2 - 2) & (np.abs(y) < side / 2 - 2)
    outside = (np.abs(x) > side / 2 + 2) | (np.abs(y) > side / 2 + 2)
    scene.set_layout(np.array([[0, 0, 0, side], [0, 0, 0, 0]], np.float32))
    one = scene.thickness().reshape(size, size, -1).numpy()
    # Rays are nearly vertical (camera 10 view widths away): 1 / cos(tilt) < 1.0002 here.
    np.testing.assert_allclose(one[inside], side, rtol=2e-4)
    assert (one[outside] == 0).all()
    scene.set_layout(np.array([[0, 0, 0, side], [0, 0, 0.5 * side, side]], np.float32))  # half of each overlaps
    two = scene.thickness().reshape(size, size, -1).numpy()
    np.testing.assert_allclose(two[inside], 2 * side, rtol=2e-4)


def test_thickness_is_cached_per_layout(tiny):
    from conftest import TINY_PHI

    first = tiny.thickness()
    assert tiny.thickness() is first
    assert tiny.thickness(spp=1) is not first and tiny.thickness(spp=1).shape == (16 * 16, 1)
    tiny.set_layout(TINY_PHI)
    again = tiny.thickness()
    assert again is not first
    torch.testing.assert_close(again, first)


def test_absent_rows_render_nothing():
    scene = make_scene(n=3)
    values = torch.tensor([0.8, 0.2, 0.1])
    scene.set_layout(np.zeros((3, 4), np.float32))
    assert (scene.thickness() == 0).all() and (scene.instance_labels() == 0).all()
    torch.testing.assert_close(scene.render(values, seed=0), torch.full((16, 16), 0.8))
    phi = np.array([[0, 0, 0, 0], [5, -4, 3, 20], [0, 0, 0, 0]], np.float32)
    scene.set_layout(phi)
    alone = make_scene(n=1)
    alone.set_layout(phi[1:2])
    torch.testing.assert_close(scene.thickness(), alone.thickness())


# -- image ----------------------------------------------------------------------------------------
def test_image_is_background_where_no_particle_and_darker_on_particles(tiny):
    from scipy.ndimage import binary_dilation

    background, absorption, floor = 0.8, 0.3, 0.1
    image = tiny.render(torch.tensor([background, absorption, floor]), seed=0).numpy()
    assert image.dtype == np.float32 and image.shape == (16, 16)
    covered = (tiny.thickness() > 0).any(dim=1).reshape(16, 16).numpy()
    far = ~binary_dilation(covered, iterations=2)  # beyond the reach of the reconstruction blur (radius 2)
    assert far.sum() > 20
    np.testing.assert_allclose(image[far], background, rtol=1e-6)
    labels = tiny.instance_labels()
    assert (image[labels > 0] < background - 0.05).all() and (image >= floor - 1e-6).all()


def test_image_formula_without_blur():
    """floor + (background - floor) * mean exp(-absorption t), checked from the cached path lengths."""
    from conftest import TINY_PHI

    scene = make_scene(filter_stddev=0.25)  # below a pixel's own box: no extra blur
    scene.set_layout(TINY_PHI)
    image = scene.render(torch.tensor([0.9, 0.05, 0.2], dtype=torch.float64), seed=0)
    t = scene.thickness().double()
    expected = 0.2 + 0.7 * torch.exp(-0.05 * t).mean(dim=1).reshape(16, 16)
    torch.testing.assert_close(image, expected)


def test_fixed_parameters_are_constants():
    fixed = {"background": {"value": 0.7}, "absorption": {"min": 0.01, "max": 0.5}}  # floor absent: 0
    scene = make_scene(transmission=fixed, n=1)
    assert [p.name for p in scene.learned] == ["absorption"]
    scene.set_layout(np.array([[0, 0, 0, 30]], np.float32))
    image = scene.render(torch.tensor([0.5]), seed=0)
    assert image[0, 0] == pytest.approx(0.7) and image[8, 8] < 0.01
    with pytest.raises(ConfigError, match="values: expected shape"):
        scene.render(torch.tensor([0.5, 0.1]), seed=0)


def _finite_difference(loss, values: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    grads = []
    for i in range(len(values)):
        step = torch.zeros_like(values)
        step[i] = h
        grads.append((loss(values + step) - loss(values - step)) / (2 * h))
    return torch.stack(grads)


@pytest.mark.parametrize("kind", ["linear", "squares", "blurred_log"])
def test_gradients_match_finite_differences(tiny, kind):
    from drgan.scene.scene import reconstruction_blur

    rng = np.random.default_rng(3)
    weights = torch.from_numpy(rng.normal(size=(16, 16)))
    target = torch.from_numpy(rng.uniform(0.2, 0.9, size=(16, 16)))
    losses = {
        "linear": lambda image: (weights * image).sum(),
        "squares": lambda image: ((image - target) ** 2).sum(),
        "blurred_log": lambda image: (weights * torch.log(reconstruction_blur(image, 1.5))).sum(),
    }

    def loss(values):
        return losses[kind](tiny.render(values, seed=0))

    values = torch.tensor([0.8, 0.12, 0.15], dtype=torch.float64, requires_grad=True)
    loss(values).backward()
    expected = _finite_difference(loss, values.detach())
    assert (expected.abs() > 1e-3).all(), expected  # every parameter matters to this loss
    torch.testing.assert_close(values.grad, expected, rtol=1e-6, atol=1e-8)


def test_the_seed_changes_nothing(tiny):
    values = torch.tensor([0.8, 0.12, 0.15])
    torch.testing.assert_close(tiny.render(values, seed=1), tiny.render(values, seed=2), rtol=0, atol=0)


# -- labels ---------------------------------------------------------------------------------------
def test_labels_exact_for_particles_at_known_positions():
    from drgan.scene.config import ParameterRange, SecondaryImaging
    from drgan.scene.parameters import MaterialParameters, noise_parameter
    from drgan.scene.scene import ParticleScene, RenderSettings, SceneSpec

    size, side = 32, 12.0
    phi = np.array([[-16, 16, 0, side], [16, 16, 0, side], [0, -14, 0, side], [0, 0, 0, 0]], np.float32)
    scene = make_scene([unit_cube()], n=4, resolution=size, spp=1)
    scene.set_layout(phi)
    labels = scene.instance_labels()
    x, y = pixel_centres(size)
    margin = 1.0  # px of the real image around the (slightly perspective) cube edges
    expected = np.zeros((size, size), int)
    unsure = np.zeros((size, size), bool)
    for k, (cx, cy, _, s) in enumerate(phi[:3], start=1):
        dist = np.maximum(np.abs(x - cx), np.abs(y - cy))
        expected[dist < s / 2 - margin] = k
        unsure |= np.abs(dist - s / 2) <= margin
    np.testing.assert_array_equal(labels[~unsure], expected[~unsure])
    assert set(np.unique(labels)) == {0, 1, 2, 3}
    # The same code as the SEM scene's labels: identical label images for the same meshes and layout.
    imaging = SecondaryImaging(particle_bsdf={"base_color": ParameterRange(value=0.5)})
    params = MaterialParameters(imaging.scene_parameters(), noise_parameter(None))
    sem = ParticleScene(
        [unit_cube()],
        4,
        SceneSpec(params, RenderSettings(resolution=size, spp=1), VIEW, stage=False),
        variant=TEST_VARIANT,
    )
    sem.set_layout(phi)
    np.testing.assert_array_equal(sem.instance_labels(), labels)


def test_overlapping_particles_split_where_their_outlines_are_equally_far_whichever_lies_in_front():
    """Transmission labels give an overlap to the particle whose own outline is farthest: for two spheres (discs of
    radii r1, r2 in projection) the curve r1 - d1 = r2 - d2 between the outlines' crossings, the same whichever is in
    front; the opaque scene's first hit gives the front sphere the whole lens."""
    from drgan.scene import particle_meshes

    size, (r1, r2), (c1, c2) = 64, (12.0, 10.0), (-8.0, 8.0)
    x, y = pixel_centres(size)
    d1, d2 = np.hypot(x - c1, y), np.hypot(x - c2, y)
    lens = (d1 < r1 - 1.0) & (d2 < r2 - 1.0)
    scene = make_scene([particle_meshes.sphere(3)], n=2, resolution=size, spp=1)
    labels = []
    for z1, z2 in ((10.0, -10.0), (-10.0, 10.0)):
        scene.set_layout(np.array([[c1, 0, z1, 2 * r1], [c2, 0, z2, 2 * r2]], np.float32))
        labels.append(scene.instance_labels())
        first = super(type(scene), scene)._trace_labels()  # the opaque scene's rule, for contrast
        assert len(np.unique(first[lens])) == 1  # one sphere takes the whole lens
    clear = (np.abs(d1 - r1) > 1.0) & (np.abs(d2 - r2) > 1.0)  # away from the outlines (perspective moves them)
    np.testing.assert_array_equal(labels[0][clear], labels[1][clear])
    margin = (r1 - d1) - (r2 - d2)  # > 0: farther from the first outline
    assert (labels[0][lens & (margin > 1.0)] == 1).all() and (labels[0][lens & (margin < -1.0)] == 2).all()
    assert (labels[0][(d1 < r1 - 1) & (d2 > r2 + 1)] == 1).all() and (
        labels[0][(d2 < r2 - 1) & (d1 > r1 + 1)] == 2
    ).all()
    assert (labels[0][(d1 > r1 + 1) & (d2 > r2 + 1)] == 0).all()


def test_farthest_outline_labels_continue_a_silhouette_cut_by_the_image_border():
    """A pixel in two silhouettes goes to the one whose outline is farther; the image border is no outline."""
    from drgan.scene.transmission import farthest_outline_labels

    silhouettes = np.zeros((8, 12, 2), bool)
    silhouettes[:, 0:7, 0] = True  # cut by the left, top and bottom borders: its only outline is at column 7
    silhouettes[2:6, 4:10, 1] = True  # inside the image: outlines all round
    labels = farthest_outline_labels(silhouettes, np.zeros((8, 12), np.int32))
    np.testing.assert_array_equal(labels[:, :4], 1)  # the first alone
    assert (labels[2:6, 4] == 1).all()  # 3 px from the first's outline, 1 px from the second's
    assert (labels[3:5, 6] == 2).all()  # 1 px from the first's outline, 2 px from the second's
    np.testing.assert_array_equal(labels[2:6, 7:10], 2)
    assert (labels[:2, 7:] == 0).all() and (labels[6:, 7:] == 0).all()


# -- configuration --------------------------------------------------------------------------------
def _material(imaging=None, **extra):
    material = {
        "name": "tem",
        "n_particles": 4,
        "particle_size_px": 10,
        "view_width": int(VIEW),
        "noise_sigma": SIGMA,
        "imaging": {"_target_": "drgan.scene.transmission.TransmissionScene", **LIMITS, **(imaging or {})},
    }
    material.update(extra)
    return material


@pytest.mark.parametrize(
    "key, value",
    [
        ("particle_bsdf", {"base_color": {"value": 0.5}}),
        ("stage_bsdf", {"base_color": {"value": 0.1}}),
        ("torus_light", {"radiance": 1.0}),
    ],
)
def test_secondary_keys_are_refused_in_a_transmission_material(key, value):
    from drgan.models import build

    with pytest.raises(ConfigError, match=f"material.imaging.{key}: Key '{key}' not in 'TransmissionImaging'"):
        build.scene_spec(_material({key: value}), {"resolution": 16, "spp": 1})


def test_imaging_and_transmission_settings_are_checked():
    from drgan.models import build
    from drgan.scene.transmission import TransmissionSpec

    spec = build.scene_spec(_material(), {"resolution": 16, "spp": 4})
    assert isinstance(spec, TransmissionSpec) and [p.name for p in spec.parameters.learned] == [
        "background",
        "absorption",
        "floor",
        "sigma",
    ]
    floorless = _material()
    del floorless["imaging"]["floor"]
    assert [p.name for p in build.scene_spec(floorless, {}).parameters.learned] == ["background", "absorption", "sigma"]
    with pytest.raises(ConfigError, match=r"material.imaging._target_='tem': not a registered scene class"):
        build.scene_spec(_material({"_target_": "tem"}), {})
    missing = _material()
    del missing["imaging"]["absorption"]
    with pytest.raises(ConfigError, match="material.imaging.absorption"):
        build.scene_spec(missing, {})
    with pytest.raises(ConfigError, match="material.imaging.gamma"):
        build.scene_spec(_material({"gamma": {"value": 1.0}}), {})
    with pytest.raises(ConfigError, match="material.imaging.background"):
        build.scene_spec(_material({"background": {"min": 0.9, "max": 0.1}}), {})
    with pytest.raises(ConfigError, match="material.imaging._target_: missing"):
        build.scene_spec(_material(imaging=None) | {"imaging": {}}, {})
    with pytest.raises(ConfigError, match="material.noise_grain_px"):
        build.scene_spec(_material(noise_grain_px=-1), {})


def test_open_meshes_are_refused():
    from drgan.core.errors import MeshError

    open_box = unit_cube()
    open_box.update_faces(np.arange(len(open_box.faces)) > 0)
    with pytest.raises(MeshError, match="not closed"):
        make_scene([open_box], n=1)


# -- noise grain ----------------------------------------------------------------------------------
def _lag1(noise: np.ndarray) -> float:
    noise = noise - noise.mean()
    return float(((noise[:, 1:] * noise[:, :-1]).mean() + (noise[1:] * noise[:-1]).mean()) / (2 * noise.var()))


def test_noise_grain_keeps_sigma_and_correlates_neighbours():
    from drgan.models.generator import add_noise

    sigma, image = 0.05, torch.full((256, 256), 0.5, dtype=torch.float64)
    correlations = []
    for grain in (0.0, 1.0, 2.0):
        noise = (add_noise(image, torch.tensor(sigma, dtype=torch.float64), seed=7, grain_px=grain) - 0.5).numpy()
        assert noise.var() == pytest.approx(sigma**2, rel=0.15), grain
        correlations.append(_lag1(noise))
    # A Gaussian blur of stddev g gives neighbours a correlation of exp(-1 / (4 g^2)) (within truncation).
    assert abs(correlations[0]) < 0.02
    assert correlations[1] == pytest.approx(np.exp(-0.25), abs=0.04)
    assert correlations[2] == pytest.approx(np.exp(-1 / 16), abs=0.04)
    assert correlations[0] < correlations[1] < correlations[2]
    white = add_noise(image, torch.tensor(sigma, dtype=torch.float64), seed=7)
    torch.testing.assert_close(white, add_noise(image, torch.tensor(sigma, dtype=torch.float64), seed=7, grain_px=0.0))


def test_grained_noise_keeps_sigma_differentiable():
    from drgan.models.generator import add_noise

    sigma = torch.tensor(0.05, requires_grad=True)
    noisy = add_noise(torch.full((32, 32), 0.5), sigma, seed=1, grain_px=1.5)
    (noisy - 0.5).square().sum().backward()
    assert sigma.grad is not None and sigma.grad > 0


# -- the material config --------------------------------------------------------------------------
def test_tio2_tsem_generator_renders_with_gradients(one_torch_thread):
    from drgan.models import build
    from drgan.scene.transmission import TransmissionScene

    cfg = compose(
        [
            "material=tio2_tsem",
            "renderer.resolution=16",
            "material.view_width=64",
            "material.particle_size_px=12",
            "renderer.spp=4",
            f"renderer.variant={TEST_VARIANT}",
            "material.n_particles=6",
            "material.n_particles_min=2",
            "material.meshes.count=3",
        ],
        config_name="train",
    )
    generator = build.build_generator(cfg)
    assert isinstance(generator.scene, TransmissionScene)
    assert generator.noise_grain_px == 1.0
    assert [p.key for p in generator.learned] == [
        "transmission.background",
        "transmission.absorption",
        "transmission.floor",
        "noise.sigma",
    ]
    phi = torch.as_tensor(build.sample_phi(cfg, 2, seed=0))
    images, values = generator.render_batch(phi)
    assert images.shape == (2, 1, 16, 16) and torch.isfinite(images).all()
    (images * torch.linspace(-1, 1, 16)).sum().backward()
    grads = [p.grad for p in generator.regressor.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0
    sample = generator.sample(phi[0].numpy(), seed=3)
    assert set(sample.parameters) == {
        "transmission.background",
        "transmission.absorption",
        "transmission.floor",
        "noise.sigma",
    }
    assert sample.labels.max() >= 1 and sample.image.min() >= 0 and sample.image.max() <= 1
