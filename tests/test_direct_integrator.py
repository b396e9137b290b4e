"""renderer.integrator=direct_light / direct_light_mis (drgan.scene.direct): prb's images in expectation,
gradients against finite differences with a linear and a non-linear loss, settings checked."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import PAPER_PARTICLE, PAPER_SIGMA, PAPER_STAGE, TEST_VARIANT, TINY_PHI, make_scene

from drgan.core.errors import ConfigError

# Learned order: stage.base_color, particle.roughness, base_color, sheen, sheen_tint, spec_tint.
MID = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])
COLOURS = (0, 2, 3, 5)  # parameters that do not steer sampling: smooth estimators under common random numbers
STEPS = [0.01, 0.1, 0.01, 0.01, 0.01, 0.01]


def scene_with(integrator, resolution=16, spp=4, grad_seed="independent", stage=PAPER_STAGE, recapture=0.0, phi=None):
    from drgan.scene import particle_meshes
    from drgan.scene.config import SecondaryImaging
    from drgan.scene.scene import ParticleScene, RenderSettings, SceneSpec

    params = SecondaryImaging(particle_bsdf=PAPER_PARTICLE, stage_bsdf=stage).material_parameters(PAPER_SIGMA)
    render = RenderSettings(resolution=resolution, spp=spp, integrator=integrator, grad_seed=grad_seed)
    phi = TINY_PHI if phi is None else phi
    spec = SceneSpec(params, render, view_width=64.0, recapture=recapture)
    scene = ParticleScene([particle_meshes.sphere(2)], len(phi), spec, variant=TEST_VARIANT)
    scene.set_layout(phi)
    return scene


def images(scene, values, seeds):
    with torch.no_grad():
        return torch.stack([scene.render(values, seed=s) for s in seeds])


@pytest.mark.parametrize("integrator", ["direct_light", "direct_light_mis"])
def test_images_match_prb_in_expectation(integrator):
    """Mean of 32 renders at spp 16 (512 samples per pixel) against prb's from other seeds.

    Tolerance: per pixel |difference| <= 4 standard errors (from the spread over seeds of both) + 1e-4,
    with at most 1 % of pixels outside; the image means agree within 1 %. A missing light strategy, a
    double-counted one or a wrong MIS weight shifts many pixels by far more (direct illumination is 100 %
    of these images).
    """
    values = torch.tensor([0.2, 0.1, 0.8, 0.3, 0.4, 0.6])  # a glossy particle: both strategies matter
    ours = images(scene_with(integrator, spp=16), values, range(32))
    prb = images(scene_with("prb", spp=16), values, range(1000, 1032))
    diff = ours.mean(0) - prb.mean(0)
    stderr = torch.sqrt(ours.var(0) / len(ours) + prb.var(0) / len(prb))
    outside = (diff.abs() > 4 * stderr + 1e-4).float().mean()
    assert outside <= 0.01, f"{float(outside):.3f} of pixels differ beyond 4 standard errors"
    assert abs(float(ours.mean() / prb.mean()) - 1) < 0.01, (float(ours.mean()), float(prb.mean()))
    assert float(prb.mean()) > 0.01  # the scene is lit


def test_with_mis_everywhere_it_is_prbs_estimator():
    """direct_light_mis draws the same random numbers for the same strategies as prb at max_depth 2, so each
    seed gives prb's image (to float rounding): the same image noise, by construction."""
    ours = images(scene_with("direct_light_mis"), MID, range(3))
    prb = images(scene_with("prb"), MID, range(3))
    torch.testing.assert_close(ours, prb, rtol=1e-4, atol=1e-5)


def test_direct_light_samples_the_bsdf_on_particles_only():
    """On the stage (fixed roughness) direct_light samples only the lights: other images per seed than
    direct_light_mis, the same pixels inside particles (same samples, same MIS there), and the price of the
    saved ray: a noisier stage (median per-pixel std x1.34 under this scene's 45-degree ring; x1.08 under
    the TiO2 SEM lights, experiments/benchmarks/train_step.md)."""
    a, b = scene_with("direct_light", resolution=32), scene_with("direct_light_mis", resolution=32)
    particles = torch.from_numpy(a.instance_labels() > 0)
    ours, mis = images(a, MID, range(12)), images(b, MID, range(12))
    assert not torch.allclose(ours, mis)
    ratio = ours.std(0) / mis.std(0).clamp_min(1e-6)
    inner = particles & (torch.nn.functional.max_pool2d((~particles).float()[None], 5, 1, 2)[0] == 0)
    assert inner.sum() > 10
    torch.testing.assert_close(ours[:, inner], mis[:, inner])  # pixels inside particles: same samples, same MIS
    assert 1.0 < float(ratio[~particles].median()) < 1.6


def ad_and_fd(scene, loss, seeds, steps=STEPS):
    """AD gradient and central finite differences with common random numbers (the same seeds both sides)."""

    def total(x):
        return sum(loss(scene.render(x, seed=s)) for s in seeds)

    x = MID.clone().requires_grad_(True)
    total(x).backward()
    fd = []
    with torch.no_grad():
        for i, h in enumerate(steps):
            e = torch.zeros_like(MID)
            e[i] = h
            fd.append(float(total(MID + e) - total(MID - e)) / (2 * h))
    return x.grad.numpy(), np.array(fd)


@pytest.mark.parametrize(
    ("integrator", "recapture"), [("direct_light", 0.0), ("direct_light_mis", 0.0), ("direct_light_mis", 0.7)]
)
def test_gradient_of_a_linear_loss_matches_finite_differences(integrator, recapture):
    """Weighted sum of the image, the adjoint on its own samples (grad_seed independent, the default), summed
    over 16 seeds: unbiased for the derivative of the expected image. |AD - FD| <= 8 % of |FD| + 2 % of the
    largest (colours); roughness, which steers BSDF sampling, within 25 % + 5 % (step 0.1). With secondary
    electrons recaptured the escape factor multiplies the samples: the same bounds."""
    scene = scene_with(integrator, spp=16, recapture=recapture)
    weight = torch.rand(16, 16, generator=torch.Generator().manual_seed(4))
    ad, fd = ad_and_fd(scene, lambda image: (image * weight).sum(), range(16))
    scale = np.abs(fd).max()
    for i in COLOURS:
        assert abs(ad[i] - fd[i]) <= 0.08 * abs(fd[i]) + 0.02 * scale, (i, ad, fd)
    assert abs(ad[1] - fd[1]) <= 0.25 * abs(fd[1]) + 0.05 * scale, (ad, fd)
    assert abs(ad[0]) > 0.1 * scale and abs(ad[2]) > 0.1 * scale  # stage and particle colour move the image


@pytest.mark.parametrize("integrator", ["direct_light", "direct_light_mis"])
def test_gradient_of_a_nonlinear_loss_matches_finite_differences(integrator):
    """Squared distance to a target image. With grad_seed=same the adjoint replays the image's own samples,
    so for parameters that do not steer sampling the AD gradient is the exact derivative of the realised
    loss: it must match finite differences with common random numbers closely (2 % + 0.5 % of the largest)."""
    scene = scene_with(integrator, spp=4, grad_seed="same")
    target = torch.rand(16, 16, generator=torch.Generator().manual_seed(5)) * 0.3
    ad, fd = ad_and_fd(scene, lambda image: ((image - target) ** 2).sum(), range(3))
    scale = np.abs(fd).max()
    for i in COLOURS:
        assert abs(ad[i] - fd[i]) <= 0.02 * abs(fd[i]) + 0.005 * scale, (i, ad, fd)
    assert abs(ad[0]) > 0.05 * scale and abs(ad[2]) > 0.05 * scale


@pytest.mark.parametrize("where", ["low", "high"])
def test_gradients_finite_at_the_limits(where):
    scene = scene_with("direct_light")
    values = torch.tensor([p.low if where == "low" else p.high for p in scene.learned], requires_grad=True)
    image = scene.render(values, seed=3)
    assert torch.isfinite(image).all() and (image >= 0).all()
    image.square().mean().backward()
    assert torch.isfinite(values.grad).all(), values.grad


def test_bsdf_sampling_follows_the_stage_roughness():
    fixed_rough = scene_with("direct_light", stage={**PAPER_STAGE, "roughness": {"value": 0.6}})
    assert fixed_rough._bsdf_sampled_shapes() == "particles"
    assert scene_with("direct_light")._bsdf_sampled_shapes() == "particles"  # Principled default 0.5
    glossy = scene_with("direct_light", stage={**PAPER_STAGE, "roughness": {"value": 0.1}})
    assert glossy._bsdf_sampled_shapes() == "particles,stage"
    learned = scene_with("direct_light", stage={**PAPER_STAGE, "roughness": {"min": 0.05, "max": 1.0}})
    assert learned._bsdf_sampled_shapes() == "particles,stage"


def test_settings_are_checked():
    from drgan.core.backend import mi
    from drgan.scene import direct
    from drgan.scene.scene import RenderSettings

    with pytest.raises(ConfigError, match=r"renderer.max_depth=3: renderer.integrator=direct_light computes direct"):
        RenderSettings(integrator="direct_light", max_depth=3)
    with pytest.raises(ConfigError, match=r"renderer.integrator='direct': expected one of .*direct_light"):
        RenderSettings(integrator="direct")
    make_scene(integrator="direct_light")  # registers the plugin for this variant
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": direct.register(), "bsdf_sampling": "nope"},
            "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
            "floor": {"type": "rectangle"},
            "light": {"type": "constant"},
        }
    )
    with pytest.raises(ValueError, match=r"bsdf_sampling names shapes the scene lacks: \['nope'\]"):
        scene.integrator().render(scene, seed=0, spp=1)


# Emitter culling traces a second, emitters-only scene with Dr.Jit's CPU ray tracer: drgan turns it off on CUDA
# (and refuses emitter_culling there), so its tests run where the variant is an llvm one.
CPU_ONLY = pytest.mark.skipif(not TEST_VARIANT.startswith("llvm"), reason="emitter culling is CPU (llvm) only")


@CPU_ONLY
@pytest.mark.parametrize("integrator", ["direct_light", "direct_light_mis"])
def test_emitter_culling_changes_no_image_or_gradient(integrator):
    """A BSDF-sampled ray is traced through the scene only if it hits the emitters' geometry: the same images
    and gradients per seed as tracing every one (the culled rays hit no emitter, so they added nothing)."""
    from drgan.core.backend import dr, mi

    scene = scene_with(integrator, resolution=24)
    integrator_object = scene.scene.integrator()
    assert integrator_object.emitter_culling  # on by default (CPU)
    # The culling scene misses rays an emitter could never receive: here straight down from above the stage.
    geometry = integrator_object._emitter_geometry(scene.scene)
    x = dr.linspace(mi.Float, -20.0, 20.0, 50)
    down = mi.Ray3f(mi.Point3f(x, -x, 5.0), mi.Vector3f(0, 0, -1))
    assert dr.count(geometry.ray_test(down))[0] == 0 and dr.count(scene.scene.ray_test(down))[0] == 50

    def render_and_grad(culling):
        integrator_object.emitter_culling = culling
        values = MID.clone().requires_grad_(True)
        image = scene.render(values, seed=7)
        (image * torch.linspace(0.5, 1.5, image.shape[-1])).sum().backward()
        return image.detach(), values.grad

    culled, traced = render_and_grad(True), render_and_grad(False)
    torch.testing.assert_close(culled[0], traced[0], rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(culled[1], traced[1], rtol=1e-4, atol=1e-6)
    assert float(culled[0].mean()) > 0.01


@CPU_ONLY
def test_emitter_geometry_is_the_emitters_and_nothing_else():
    """Mesh emitters are copied triangle for triangle; another shape becomes a box around it; delta emitters
    are left out; an environment emitter (reached by rays that hit nothing) turns culling off."""
    from drgan.core.backend import dr, mi
    from drgan.scene import direct

    scene = scene_with("direct_light_mis")
    geometry = direct.emitter_geometry(scene.scene)
    lights = {s.id(): s for s in scene.scene.shapes() if s.emitter() is not None}
    assert set(lights) == {"torus_light", "top_light"}
    copies = sorted((np.array(s.vertex_positions_buffer()).tolist() for s in geometry.shapes()), key=len)
    originals = sorted((np.array(s.vertex_positions_buffer()).tolist() for s in lights.values()), key=len)
    assert copies == originals  # the same vertices, so a ray hits a copy wherever it hits the light

    def scene_of(**emitters):
        return mi.load_dict({"type": "scene", "floor": {"type": "rectangle"}, **emitters})

    sphere = {"type": "sphere", "center": [0, 0, 3], "radius": 0.5, "emitter": {"type": "area"}}
    boxed = direct.emitter_geometry(scene_of(lamp=sphere, point={"type": "point", "position": [0, 0, 1]}))
    (box,) = boxed.shapes()
    assert box.face_count() == 12
    assert np.all(np.array(box.bbox().min) <= [-0.5, -0.5, 2.5]) and np.all(np.array(box.bbox().max) >= [0.5, 0.5, 3.5])
    assert np.all(np.array(box.bbox().min) > [-0.51, -0.51, 2.49])  # a little larger, not a lot
    # Every ray from below that hits the sphere hits its box, and upward rays beside it miss both.
    x = dr.linspace(mi.Float, -0.7, 0.7, 101)
    rays = mi.Ray3f(mi.Point3f(x, x * 0.3, 0.0), mi.Vector3f(0, 0, 1))
    lamp = scene_of(lamp=sphere)  # held: the traced call runs when its result is read
    hits_sphere, hits_box = lamp.ray_test(rays), boxed.ray_test(rays)
    assert dr.all(~hits_sphere | hits_box) and dr.count(hits_sphere)[0] > 10 and not dr.all(hits_box)
    assert direct.emitter_geometry(scene_of(sky={"type": "constant"})) is None


@CPU_ONLY
def test_culling_in_a_plain_mitsuba_scene():
    """The integrator is a Mitsuba plugin: in a scene loaded from a dict (emitters a rectangle and a sphere, the
    floor diffuse, a point light too), culling on and off give the same image."""
    from drgan.core.backend import mi
    from drgan.scene import direct

    make_scene(integrator="direct_light")  # registers the plugin for this variant

    def render(culling):
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": direct.register(), "emitter_culling": culling},
                "sensor": {
                    "type": "perspective",
                    "to_world": mi.ScalarTransform4f().look_at(origin=[0, -4, 4], target=[0, 0, 0], up=[0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 16},
                },
                "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([3, 3, 1])},
                "ball": {"type": "sphere", "center": [0, 0, 0.5], "radius": 0.5, "bsdf": {"type": "roughconductor"}},
                "panel": {
                    "type": "rectangle",
                    "to_world": mi.ScalarTransform4f().translate([1, 0, 2]).rotate([1, 0, 0], 180),
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 3.0}},
                },
                "bulb": {"type": "sphere", "center": [-1, 1, 1.5], "radius": 0.2, "emitter": {"type": "area"}},
                "point": {"type": "point", "position": [0, -1, 2], "intensity": {"type": "rgb", "value": 2.0}},
            }
        )
        return np.array(mi.render(scene, seed=3, spp=16))

    culled, traced = render(True), render(False)
    np.testing.assert_allclose(culled, traced, rtol=1e-6, atol=1e-7)
    assert culled.mean() > 0.01


TOUCHING = np.array([[-9.5, 0, 10, 20], [9.5, 0, 10, 20]], dtype=np.float32)  # two spheres of 20 px, side by side


@pytest.mark.parametrize("integrator", ["direct_light", "direct_light_mis"])
def test_recaptured_electrons_darken_the_neck_between_touching_particles_not_their_tops(integrator):
    """material.imaging.recapture: a point whose hemisphere the neighbour covers loses that share of its signal.
    The neck between two touching spheres (its hemisphere half covered) darkens by about recapture x 0.3-0.6; a
    sphere's top (nothing above it) keeps its grey; recapture 0 draws no extra random number (the image of before,
    per seed, to float rounding: the LLVM backend's threads may add a pixel's samples in another order, ~3e-8; an
    extra random number would move every pixel by the sampling noise, ~1e-2)."""
    plain = scene_with(integrator, resolution=32, spp=16, phi=TOUCHING)
    none = scene_with(integrator, resolution=32, spp=16, phi=TOUCHING, recapture=0.0)
    full = scene_with(integrator, resolution=32, spp=16, phi=TOUCHING, recapture=1.0)
    torch.testing.assert_close(images(none, MID, [0]), images(plain, MID, [0]), rtol=0, atol=1e-6)
    a, b = images(plain, MID, range(8)).mean(0), images(full, MID, range(8)).mean(0)
    labels = plain.instance_labels()
    assert labels[16, 10] == labels[16, 15] != 0 and 0 != labels[16, 16] != labels[16, 15]  # the neck: 15 | 16
    top, neck = (16, 10), (16, slice(15, 17))  # the left sphere's centre; the two pixels either side of the contact
    assert abs(float(b[top] / a[top]) - 1) < 0.03, (float(a[top]), float(b[top]))
    assert 0.3 < float(b[neck].mean() / a[neck].mean()) < 0.85, (a[neck], b[neck])


def test_recapture_is_checked_before_any_render():
    from drgan.scene.config import SecondaryImaging

    with pytest.raises(ConfigError, match=r"material.imaging.recapture=1.5: expected a share in \[0, 1\]"):
        SecondaryImaging(particle_bsdf=PAPER_PARTICLE, stage_bsdf=PAPER_STAGE, recapture=1.5)
    with pytest.raises(ConfigError, match=r"recapture=0.5 needs renderer.integrator=direct_light or direct_light_mis"):
        scene_with("prb", recapture=0.5)
