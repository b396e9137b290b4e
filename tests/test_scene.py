"""The differentiable scene: gradients against finite differences, limits, labels, minimal scene, kernels."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import PAPER_PARTICLE, PAPER_STAGE, TINY_PHI, make_scene

from drgan.core.errors import ConfigError

# Learned order: stage.base_color, particle.roughness, base_color, sheen, sheen_tint, spec_tint.
MID = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])


def weighted_sum(scene, values, seeds, weight):
    return sum((scene.render(values, seed=s) * weight).sum() for s in seeds)


def ad_and_fd(scene, x0, seeds, weight, steps):
    """AD gradient and central finite differences with common random numbers (same seeds on both sides)."""
    x = x0.clone().requires_grad_(True)
    weighted_sum(scene, x, seeds, weight).backward()
    fd = []
    with torch.no_grad():
        for i, h in enumerate(steps):
            e = torch.zeros_like(x0)
            e[i] = h
            fd.append(
                float(weighted_sum(scene, x0 + e, seeds, weight) - weighted_sum(scene, x0 - e, seeds, weight)) / (2 * h)
            )
    return x.grad.numpy(), np.array(fd)


def test_gradients_match_finite_differences():
    """Tolerance: |AD - FD| <= 5 % of |FD| + 1 % of the largest gradient (10 % for roughness).

    Roughness changes the BSDF's importance sampling, so its estimator is not smooth in the parameter
    even with common random numbers: it gets a wider step (0.1) and a looser relative tolerance.
    """
    scene = make_scene(resolution=16, spp=16)
    scene.set_layout(TINY_PHI)
    weight = torch.rand(16, 16, generator=torch.Generator().manual_seed(1))
    steps = [0.01, 0.1, 0.01, 0.01, 0.01, 0.01]
    ad, fd = ad_and_fd(scene, MID, range(24), weight, steps)
    assert np.isfinite(ad).all()
    scale = np.abs(fd).max()
    rel = np.array([0.05, 0.10, 0.05, 0.05, 0.05, 0.05])
    bad = np.abs(ad - fd) > rel * np.abs(fd) + 0.01 * scale
    assert not bad.any(), f"AD {ad} vs FD {fd}"
    # The gradients are informative, not all zero: stage and particle colour move the image.
    assert abs(ad[0]) > 0.1 * scale and abs(ad[2]) > 0.1 * scale


@pytest.mark.parametrize("integrator", ["direct_projective", "prb"])
def test_other_integrator_agrees(integrator):
    scene = make_scene(resolution=16, spp=16, integrator=integrator)
    scene.set_layout(TINY_PHI)
    weight = torch.rand(16, 16, generator=torch.Generator().manual_seed(2))
    x = MID.clone()
    ad, fd = ad_and_fd(scene, x, range(8), weight, [0.01, 0.1, 0.01, 0.01, 0.01, 0.01])
    for i in (0, 2, 3, 5):  # colour-like parameters: smooth estimators
        assert abs(ad[i] - fd[i]) <= 0.08 * abs(fd[i]) + 0.01 * np.abs(fd).max(), (i, ad, fd)


def test_fewer_adjoint_samples_keep_the_gradient_unbiased():
    """renderer.grad_spp: the image is rendered at spp 16 and unchanged, its gradient from an adjoint pass
    at spp 4; summed over seeds it agrees with finite differences of the spp 16 image, and it is a
    different estimate per seed than the full-spp adjoint (the setting is used)."""
    scene = make_scene(resolution=16, spp=16, integrator="prb")
    scene.set_layout(TINY_PHI)
    weight = torch.rand(16, 16, generator=torch.Generator().manual_seed(3))
    steps = [0.01, 0.1, 0.01, 0.01, 0.01, 0.01]
    _, fd = ad_and_fd(scene, MID, range(24), weight, steps)

    def adjoint(grad_spp, seeds):
        x = MID.clone().requires_grad_(True)
        images = [scene.render(x, seed=s, grad_spp=grad_spp) for s in seeds]
        sum((im * weight).sum() for im in images).backward()
        return x.grad.numpy(), torch.stack(images).detach()

    cheap, images_cheap = adjoint(4, range(24))
    full, images_full = adjoint(16, range(1))
    torch.testing.assert_close(images_cheap[0], images_full[0])  # the image itself does not change
    assert not np.allclose(adjoint(4, range(1))[0], full), "grad_spp had no effect on the adjoint pass"
    for i in (0, 2, 3, 5):  # colour-like parameters: smooth estimators
        assert abs(cheap[i] - fd[i]) <= 0.08 * abs(fd[i]) + 0.02 * np.abs(fd).max(), (i, cheap, fd)


@pytest.mark.parametrize("where", ["low", "high"])
def test_gradients_finite_at_limits(tiny_scene, where):
    learned = tiny_scene.learned
    values = torch.tensor([p.low if where == "low" else p.high for p in learned], requires_grad=True)
    image = tiny_scene.render(values, seed=3)
    assert torch.isfinite(image).all() and (image >= 0).all()
    image.square().mean().backward()
    assert torch.isfinite(values.grad).all(), values.grad


def test_differentiable_parameters_are_exactly_the_learned_ones():
    from drgan.core.backend import dr, mi

    particle = dict(PAPER_PARTICLE)
    particle["sheen_tint"] = {"value": 0.5}  # fixed: must not carry a gradient
    particle["metallic"] = {"value": 0.2}
    scene = make_scene(particle=particle)
    scene.set_layout(TINY_PHI)
    values = torch.full((len(scene.learned),), 0.5, requires_grad=True)
    scene.render(values, seed=0).sum().backward()
    params = mi.traverse(scene.scene)
    enabled = {k for k in params.keys() if dr.grad_enabled(params[k])}
    expected = {
        "stage.bsdf.base_color.value",
        "particles.bsdf.roughness.value",
        "particles.bsdf.base_color.value",
        "particles.bsdf.sheen.value",
        "particles.bsdf.spec_tint.value",
    }
    assert enabled == expected
    assert params["particles.bsdf.sheen_tint.value"][0] == pytest.approx(0.5)
    assert params["particles.bsdf.metallic.value"][0] == pytest.approx(0.2)


def test_unused_scene_elements_are_not_built():
    scene = make_scene(stage=None, top_light=None)
    ids = {shape.id() for shape in scene.scene.shapes()}
    assert ids == {"particles", "torus_light"}
    assert len(scene.scene.emitters()) == 1
    full = make_scene()
    assert {shape.id() for shape in full.scene.shapes()} == {"particles", "stage", "torus_light", "top_light"}


def test_stage_and_top_light_are_mitsubas_rectangles_as_triangles():
    """`rectangle_mesh`: the surface of Mitsuba's ``rectangle`` under the same transform (rays hit it at the same
    t with the same normal, and miss it alike), as two plain triangles; the top light faces the stage."""
    from drgan.core.backend import dr, mi
    from drgan.scene.scene import rectangle_mesh

    scene = make_scene()
    shapes = {shape.id(): shape for shape in scene.scene.shapes()}
    assert shapes["stage"].is_mesh() and shapes["top_light"].is_mesh()
    assert shapes["stage"].face_count() == 2 and shapes["top_light"].emitter() is not None
    up = mi.Ray3f(mi.Point3f(0.0, 0.0, 1.0), mi.Vector3f(0, 0, 1))
    light = scene.scene.ray_intersect(up)
    assert light.shape == mi.ShapePtr(shapes["top_light"]) and light.n.z[0] < -0.99  # emits downwards
    to_world = mi.ScalarTransform4f().translate([1, -2, 5]).rotate([1, 0.3, 0], 160).scale([3, 2, 1])
    triangles = mi.load_dict({"type": "scene", "shape": rectangle_mesh("lamp", to_world)})
    rectangle = mi.load_dict({"type": "scene", "shape": {"type": "rectangle", "to_world": to_world}})
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (2, 4000)).astype(np.float32)
    rays = mi.Ray3f(mi.Point3f(mi.Float(xy[0]), mi.Float(xy[1]), 0.0), mi.Vector3f(0.05, -0.1, 1.0))
    # Each scene's rays in a kernel of their own: OptiX (cuda_ad_rgb) disables a ray tracing operation whose kernel
    # uses two scenes' shader binding tables, and the lazily fused comparisons below would make that one kernel.
    a = triangles.ray_intersect(rays)
    dr.eval(a)
    b = rectangle.ray_intersect(rays)
    dr.eval(b)
    hits = np.array(a.is_valid())
    assert np.array_equal(hits, np.array(b.is_valid())) and 500 < hits.sum() < 3500
    hit = a.is_valid()
    assert dr.max(dr.select(hit, dr.abs(a.t - b.t) / b.t, 0.0))[0] < 1e-6
    assert dr.min(dr.select(hit, dr.dot(a.n, b.n), 1.0))[0] > 1 - 1e-6
    area = [s.shapes()[0].surface_area()[0] for s in (triangles, rectangle)]
    assert area[0] == pytest.approx(area[1], rel=1e-5)  # so an emitter on it has the same pdf
    assert shapes["stage"].surface_area()[0] == pytest.approx((8 * scene.spec.view_width) ** 2, rel=1e-5)


def test_new_layouts_compile_no_new_kernels(tiny_scene):
    from drgan.core.backend import dr

    rng = np.random.default_rng(0)
    values = MID.clone().requires_grad_(True)

    def step(seed):
        phi = TINY_PHI.copy()
        phi[:, :2] += rng.uniform(-5, 5, size=(4, 2)).astype(np.float32)
        phi[:, 3] *= rng.uniform(0.8, 1.2, size=4).astype(np.float32)
        tiny_scene.set_layout(phi)
        tiny_scene.render(values, seed=seed).mean().backward()

    step(0)
    step(1)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history_clear()
        step(2)
        warm = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        step(3)
        step(4)
        later = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
    assert warm and later <= warm, f"{len(later - warm)} kernels compiled for new layouts/seeds"


def test_labels_align_with_render():
    """White particles on no stage (black): the thresholded render matches the labels."""
    particle = {"base_color": {"value": 1.0}, "roughness": {"value": 1.0}}
    from drgan.scene.scene import TopLight

    light = TopLight(radiance=1.0, size=2.0)
    scene = make_scene(
        resolution=64, spp=64, particle=particle, stage=None, filter_stddev=0.25, torus_light=None, top_light=light
    )
    scene.set_layout(TINY_PHI)
    image = scene.render(torch.zeros(0), seed=0).numpy()
    labels = scene.instance_labels()
    assert set(np.unique(labels)) == {0, 1, 2, 3, 4}
    # Threshold well below the particle level: Monte Carlo noise inside particles must not read as background.
    bright = image > 0.25 * np.median(image[labels > 0])
    iou = (bright & (labels > 0)).sum() / (bright | (labels > 0)).sum()
    assert iou >= 0.95, iou


def test_labels_are_occlusion_correct():
    scene = make_scene(resolution=32, n=2)
    # Particle 2 sits above particle 1 at the same x, y: from above only particle 2 is visible there.
    scene.set_layout(np.array([[0, 0, 10, 20], [0, 0, 30, 12]], dtype=np.float32))
    labels = scene.instance_labels()
    assert labels[16, 16] == 2
    assert (labels == 1).any() and (labels == 2).sum() < (labels == 1).sum() + (labels == 2).sum()


def test_label_geometry_matches_layout():
    """A particle at +x, +y shows in the right half, top rows (image y runs down)."""
    scene = make_scene(resolution=32, n=1)
    scene.set_layout(np.array([[16, 16, 5, 10]], dtype=np.float32))
    rows, cols = np.nonzero(scene.instance_labels())
    # Centre (16, 16) px in a 64 px view -> pixel (8, 24) of 32 (x right, y up).
    assert abs(cols.mean() - 24) < 1.0 and abs(rows.mean() - 8) < 1.0
    assert abs(np.sqrt(len(rows) / np.pi) - 2.5) < 0.5  # radius 5 px of 64 -> 2.5 of 32 render px


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"spp": -4}, "spp"),
        ({"spp": 10}, "perfect square"),
        ({"resolution": 0}, "resolution"),
        ({"integrator": "path_magic"}, "integrator"),
        ({"grad_spp": 8}, "renderer.grad_spp=8.*perfect square"),
    ],
)
def test_bad_render_settings_fail_clearly(kwargs, match):
    from drgan.scene.scene import RenderSettings

    with pytest.raises(ConfigError, match=match):
        RenderSettings(**kwargs)


@pytest.mark.parametrize(
    "particle, match",
    [
        ({"roughness": {"min": 2.0, "max": 1.0}}, "min=2.0 > max=1.0"),
        ({"roughness": {"min": -1.0, "max": 1.0}}, r"roughness\.min=-1\.0: expected a finite number >= 0"),
        ({"shininess": {"min": 0.0, "max": 1.0}}, "unknown Principled-BSDF parameter"),
        ({"roughness": {"min": 0.1}}, "expected keys"),
        ({"roughness": {"min": 0.1, "max": float("nan")}}, "finite"),
    ],
)
def test_bad_limits_fail_clearly(particle, match):
    from drgan.scene.config import SecondaryImaging

    with pytest.raises(ConfigError, match=match):
        SecondaryImaging(particle_bsdf=particle, stage_bsdf=PAPER_STAGE).material_parameters({"min": 0.001, "max": 0.1})


def test_bad_layout_fails_clearly(tiny_scene):
    with pytest.raises(ConfigError, match=r"expected shape \(4, 4\)"):
        tiny_scene.set_layout(np.zeros((3, 4), np.float32))
    bad = TINY_PHI.copy()
    bad[0, 3] = 0
    with pytest.raises(ConfigError, match="scales"):
        tiny_scene.set_layout(bad)
    tiny_scene.set_layout(TINY_PHI)


@pytest.mark.parametrize("stage", [PAPER_STAGE, None], ids=["stage", "no_stage"])
def test_an_all_zero_row_is_an_absent_particle(stage):
    """A 4-particle scene whose last two rows are zero renders and labels like a 2-particle scene
    (same meshes, same seed): the absent meshes are neither seen, nor hit, nor cast shadows."""
    kw = {"resolution": 24, "spp": 4, "stage": stage}
    if stage is None:
        kw["particle"] = {"base_color": {"value": 1.0}, "roughness": {"value": 1.0}}
    four, two = make_scene(n=4, **kw), make_scene(n=2, **kw)
    values = MID if stage is not None else torch.zeros(0)
    phi = TINY_PHI.copy()
    phi[2:] = 0
    four.set_layout(phi)
    two.set_layout(TINY_PHI[:2])
    np.testing.assert_allclose(four.render(values, seed=3).numpy(), two.render(values, seed=3).numpy(), atol=1e-5)
    np.testing.assert_array_equal(four.instance_labels(), two.instance_labels())
    assert set(np.unique(four.instance_labels())) == {0, 1, 2}
    np.testing.assert_array_equal(four.layout, phi)  # the layout as given, for the adjoint pass to restore


def test_box_render_plus_blur_matches_mitsubas_gaussian_filter():
    """The Gaussian reconstruction filter applied after a box-filtered render gives Mitsuba's image."""
    from drgan.core.backend import mi

    scene = make_scene(resolution=32, spp=64, filter_stddev=1.5)
    scene.set_layout(TINY_PHI)
    values = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])
    ours = sum(scene.render(values, seed=s) for s in range(4)) / 4
    reference_dict = scene._scene_dict()
    reference_dict["sensor"]["film"]["rfilter"] = {"type": "gaussian", "stddev": 1.5}
    reference_scene = mi.load_dict(reference_dict)
    params = mi.traverse(reference_scene)
    for key, value in zip(scene._learned_keys, values.tolist()):
        params[key] = value
    params["particles.vertex_positions"] = mi.traverse(scene.scene)["particles.vertex_positions"]
    params.update()
    reference = sum(np.array(mi.render(reference_scene, seed=s)).mean(-1) for s in range(4)) / 4
    inner = (slice(4, -4), slice(4, -4))  # borders differ: Mitsuba renormalises its cut footprint
    error = np.abs(ours.numpy()[inner] - reference[inner]).mean() / reference[inner].mean()
    blurred_less = (
        np.abs(np.array(mi.render(scene.scene, seed=0)).mean(-1)[inner] - reference[inner]).mean()
        / reference[inner].mean()
    )
    assert error < 0.05 and error < 0.5 * blurred_less, (error, blurred_less)


# --- ring light ---------------------------------------------------------------------------------------------


def _particle_noise(scene) -> tuple[float, float]:
    """(mean, Monte Carlo noise) over particle pixels, from two renders with different seeds."""
    labels = scene.instance_labels() > 0
    a, b = (scene.render(MID, seed=s).detach().numpy() for s in (1, 2))
    return float(a[labels].mean()), float(((a - b)[labels] / np.sqrt(2)).std())


def test_band_light_faces_the_scene():
    from drgan.scene.scene import TorusLight, torus_light_mesh

    band = torus_light_mesh(TorusLight(shape="band"), 256)
    towards_centre = np.einsum("fk,fk->f", band.face_normals, -band.triangles_center)
    assert (towards_centre > 0).all()
    # The strip spans the tube's extent: 2 x minor radius wide, centred on the tube's centre circle.
    radial = np.hypot(band.vertices[:, 0], band.vertices[:, 1])
    centre = np.array([radial.mean(), band.vertices[:, 2].mean()])
    np.testing.assert_allclose(centre, [256.0, 256.0], rtol=1e-6)
    widths = np.hypot(radial[:128] - radial[128:], band.vertices[:128, 2] - band.vertices[128:, 2])
    np.testing.assert_allclose(widths, 2 * 0.3 * 256, rtol=1e-6)


def test_band_light_lights_like_the_torus_with_less_noise():
    """Same ring of directions: similar brightness; with next-event estimation, clearly less noise."""
    from drgan.scene.scene import TorusLight

    stats = {}
    for shape in ("torus", "band"):
        scene = make_scene(resolution=32, spp=4, integrator="prb", torus_light=TorusLight(shape=shape), top_light=None)
        scene.set_layout(TINY_PHI)
        stats[shape] = _particle_noise(scene)
    (torus_mean, torus_noise), (band_mean, band_noise) = stats["torus"], stats["band"]
    assert band_mean == pytest.approx(torus_mean, rel=0.2)
    assert band_noise < 0.8 * torus_noise


def test_culled_torus_lights_the_scene_like_the_whole_torus(monkeypatch):
    import trimesh

    import drgan.scene.scene as scene_module
    from drgan.scene.scene import TorusLight

    light = TorusLight(shape="torus")
    culled = scene_module.torus_light_mesh(light, 64.0)
    whole = trimesh.creation.torus(major_radius=64.0, minor_radius=0.3 * 64.0)
    assert 0.4 * len(whole.faces) < len(culled.faces) < 0.8 * len(whole.faces)

    def render_mean(mesh_fn):
        monkeypatch.setattr(scene_module, "torus_light_mesh", mesh_fn)
        scene = make_scene(resolution=16, spp=256, integrator="prb", torus_light=light, top_light=None)
        scene.set_layout(TINY_PHI)
        return scene.render(MID, seed=3).detach().numpy()

    def whole_torus(light, w):
        ring = trimesh.creation.torus(major_radius=light.major_radius * w, minor_radius=light.minor_radius * w)
        ring.apply_translation([0, 0, light.height * w])
        return ring

    reference = render_mean(whole_torus)
    cut = render_mean(lambda light, w: culled)
    # Whole-image brightness equal within Monte Carlo error (the culled faces light nothing in view).
    assert cut.mean() == pytest.approx(reference.mean(), rel=0.03)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"shape": "cylinder"}, "shape"), ({"minor_radius": 2.0}, "minor_radius"), ({"radiance": -1.0}, "radiance")],
)
def test_bad_ring_light_is_refused(kwargs, match):
    from drgan.core.errors import ConfigError
    from drgan.scene.scene import TorusLight

    with pytest.raises(ConfigError, match=match):
        TorusLight(**kwargs)
