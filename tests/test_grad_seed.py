"""renderer.grad_seed: which samples the adjoint pass uses, tested with a non-linear (squared-error) loss.

A linear loss cannot tell the two estimators apart, so every test here uses L(I) = mean((I - T)^2):
- "same" replays the image's own samples: its gradient is the derivative of the realised noisy image,
  i.e. the common-random-numbers finite difference of L(render(seed)) at that very seed;
- "independent" runs the adjoint with a derived seed: its gradient is L'(I_seed) contracted with the
  derivative of another, independent render, so over seeds it averages to the gradient of L(E[I]).
Only base colours are learned: for fixed samples the image is affine in them (no sampling depends on them),
so a central difference is exact up to float32 rounding and the pathwise comparison can be tight.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import PAPER_SIGMA, PAPER_STAGE, TEST_VARIANT, TINY_PHI

H = 0.02  # finite-difference step, in base-colour units (values 0.2 and 0.5)
THETA = torch.tensor([0.2, 0.5])  # stage.base_color, particle.base_color


def grad_scene(grad_seed: str, integrator: str = "prb"):
    from drgan.scene import particle_meshes
    from drgan.scene.config import SecondaryImaging
    from drgan.scene.scene import ParticleScene, RenderSettings, SceneSpec

    params = SecondaryImaging(
        particle_bsdf={"base_color": {"min": 0.01, "max": 5.0}}, stage_bsdf=PAPER_STAGE
    ).material_parameters(PAPER_SIGMA)
    spec = SceneSpec(
        params, RenderSettings(resolution=16, spp=4, integrator=integrator, grad_seed=grad_seed), view_width=64.0
    )
    scene = ParticleScene([particle_meshes.sphere(2)], len(TINY_PHI), spec, variant=TEST_VARIANT)
    scene.set_layout(TINY_PHI)
    assert [p.key for p in scene.learned] == ["stage.base_color", "particle.base_color"]
    return scene


@pytest.fixture(scope="module")
def scenes():
    return {mode: grad_scene(mode) for mode in ("same", "independent")}


@pytest.fixture(scope="module")
def target(scenes):
    with torch.no_grad():  # a nearly noise-free image at other base colours
        return scenes["same"].render(torch.tensor([0.3, 0.8]), seed=12345, spp=256).double()


def mse(image, target):
    return ((image.double() - target) ** 2).mean()


def gradient(scene, target, seed, spp=4):
    x = THETA.clone().requires_grad_(True)
    mse(scene.render(x, seed=seed, spp=spp, grad_spp=spp), target).backward()
    return x.grad.double().numpy()


def pathwise_fd(scene, target, seed, spp=4):
    """Central difference of L(render(seed)) with common random numbers: the realised image's derivative."""
    out = []
    for j in range(len(THETA)):
        step = torch.zeros_like(THETA)
        step[j] = H
        with torch.no_grad():
            up, down = (mse(scene.render(THETA + s, seed=seed, spp=spp), target) for s in (step, -step))
        out.append(float(up - down) / (2 * H))
    return np.array(out)


def test_adjoint_seed_is_derived_deterministic_and_never_the_primal():
    from drgan.scene.scene import adjoint_seed

    seeds = [0, 1, 2, 12345, 0x9E3779B9, 0xFFFFFFFF] + list(range(1000))
    for seed in seeds:
        derived = adjoint_seed(seed, "independent")
        assert derived != seed and 0 <= derived <= 0xFFFFFFFF
        assert derived == adjoint_seed(seed, "independent")  # deterministic
        assert adjoint_seed(seed, "same") == seed
    # scattered, not an offset: no adjoint seed of the first 1000 steps is the image seed of one of them
    assert not {adjoint_seed(s, "independent") for s in range(1000)} & set(range(1000))
    assert adjoint_seed(2**32 + 7, "independent") == adjoint_seed(7, "independent")  # 32-bit, as render() masks


def test_bad_grad_seed_names_the_setting():
    from drgan.core.errors import ConfigError
    from drgan.models.build import scene_spec
    from drgan.scene.scene import RenderSettings

    with pytest.raises(ConfigError, match=r"renderer\.grad_seed='Same'.*independent, same"):
        RenderSettings(grad_seed="Same")
    material = {
        "name": "spheres",
        "n_particles": 2,
        "particle_size_px": 8,
        "view_width": 32,
        "filter_stddev": 0.5,
        "imaging": {
            "_target_": "drgan.scene.scene.ParticleScene",
            "particle_bsdf": {"base_color": {"min": 0.1, "max": 1.0}},
        },
    }
    with pytest.raises(ConfigError, match=r"renderer\.grad_seed='decorrelated'"):
        scene_spec(material, {"grad_seed": "decorrelated", "spp": 4})
    assert scene_spec(material, {"grad_seed": "independent"}).render.grad_seed == "independent"
    assert scene_spec(material, {}).render.grad_seed == RenderSettings().grad_seed


def test_same_is_the_derivative_of_the_realised_noisy_image(scenes, target):
    """Autograd with "same" equals the common-random-numbers FD at the same seed. Tolerance: the loss is
    quadratic in the image and the image affine in base colours, so the central difference is exact but for
    float32 rounding of images ~0.1 (relative ~1e-5 after dividing by 2h); rtol 1e-3 leaves room for that."""
    for seed in (0, 7):
        np.testing.assert_allclose(
            gradient(scenes["same"], target, seed), pathwise_fd(scenes["same"], target, seed), rtol=1e-3
        )


def test_independent_is_not_the_realised_images_derivative(scenes, target):
    """With "independent" one seed's gradient misses that pathwise FD by far more than its rounding (~20 % here:
    the derivative comes from other samples than the image's)."""
    for seed in (0, 7):
        got, fd = gradient(scenes["independent"], target, seed), pathwise_fd(scenes["same"], target, seed)
        assert np.max(np.abs(got - fd) / np.abs(fd)) > 0.05, (got, fd)


def test_independent_adjoint_runs_with_the_derived_seed(scenes, target):
    """Exactly: the independent gradient at seed k is L'(I_k), held fixed, contracted with the derivative of the
    image rendered at adjoint_seed(k) (a linear functional, where both settings agree)."""
    from drgan.scene.scene import adjoint_seed

    seed = 3
    with torch.no_grad():
        image = scenes["same"].render(THETA, seed=seed)
    weight = 2 * (image.double() - target) / image.numel()  # dL/dI at the seed-k image
    x = THETA.clone().requires_grad_(True)
    (scenes["same"].render(x, seed=adjoint_seed(seed, "independent")).double() * weight).sum().backward()
    np.testing.assert_allclose(gradient(scenes["independent"], target, seed), x.grad.double().numpy(), rtol=1e-4)
    assert np.max(np.abs(gradient(scenes["same"], target, seed) / x.grad.double().numpy() - 1)) > 0.05


def test_over_seeds_independent_follows_the_loss_of_the_expected_image(scenes, target):
    """Mean over 16 seeds at spp 1 (where the Monte Carlo grain is largest) against d L(E[I]) / d theta.
    For a squared error L' is linear, so "independent" is unbiased for it: within 4 standard errors. "same"
    also differentiates the grain's own contribution to the loss (d/dtheta of the pixel variance) and misses
    it by more than 6 standard errors (measured: ~34 and ~14 for the two parameters)."""
    # d L(E[I]): L' at one spp-1024 image, the central difference of another (independent seeds, common
    # random numbers at +- h): no grain of the reference enters, and the product is exact for a squared error.
    ref = scenes["same"]
    r1 = ref.render(THETA, seed=777, spp=1024).requires_grad_(True)
    (dloss,) = torch.autograd.grad(mse(r1, target), r1)
    expected = []
    for j in range(len(THETA)):
        step = torch.zeros_like(THETA)
        step[j] = H
        with torch.no_grad():
            up, down = (ref.render(THETA + s, seed=778, spp=1024).double() for s in (step, -step))
        expected.append(float((dloss.double() * (up - down)).sum()) / (2 * H))
    expected = np.array(expected)

    seeds = range(100, 116)
    z = {}
    for mode, scene in scenes.items():
        g = np.array([gradient(scene, target, s, spp=1) for s in seeds])
        z[mode] = np.abs(g.mean(0) - expected) / (g.std(0, ddof=1) / np.sqrt(len(g)))
    assert np.all(z["independent"] < 4), z
    assert np.all(z["same"] > 6), z
