"""Numerical stability at the extremes of every setting: images finite and in [0, 1], gradients finite."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import TINY_PHI, make_scene

from drgan.models.generator import Generator


def check_render(scene, phi, values, seed=0, spp=None):
    """Render with gradients, then return (image, grad): both must be finite."""
    scene.set_layout(phi)
    x = values.clone().requires_grad_(True)
    image = scene.render(x, seed=seed, spp=spp)
    image.square().mean().backward()
    assert torch.isfinite(image).all(), "non-finite pixels"
    assert (image >= 0).all(), "negative radiance"
    assert torch.isfinite(x.grad).all(), f"non-finite gradient {x.grad}"
    labels = scene.instance_labels()
    assert labels.shape == image.shape and labels.min() >= 0 and labels.max() <= scene.n_particles
    return image, x.grad, labels


@pytest.fixture(scope="module")
def scene():
    return make_scene(resolution=16, spp=1)


MID = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])


@pytest.mark.parametrize("index", range(6))
@pytest.mark.parametrize("end", ["low", "high"])
def test_each_parameter_alone_at_its_limit(scene, index, end):
    values = MID.clone()
    p = scene.learned[index]
    values[index] = p.low if end == "low" else p.high
    check_render(scene, TINY_PHI, values)


@pytest.mark.parametrize("index, step", [(0, 0.005), (2, 0.02), (3, 0.02), (5, 0.02)])
def test_ad_matches_fd_at_upper_limits(index, step):
    """Colour-like parameters are smooth up to their upper limits (radiance is not clamped in the render)."""
    scene = make_scene(resolution=16, spp=16)
    scene.set_layout(TINY_PHI)
    values = torch.tensor([p.high for p in scene.learned])
    values[index] -= step  # stay inside the limit for the central difference
    weight = torch.rand(16, 16, generator=torch.Generator().manual_seed(4))
    seeds = range(8)

    def f(v):
        return sum(float((scene.render(v, seed=s) * weight).sum()) for s in seeds)

    x = values.clone().requires_grad_(True)
    sum((scene.render(x, seed=s) * weight).sum() for s in seeds).backward()
    e = torch.zeros_like(values)
    e[index] = step
    fd = (f(values + e) - f(values - e)) / (2 * step)
    assert abs(float(x.grad[index]) - fd) <= 0.08 * abs(fd) + 1e-3, (float(x.grad[index]), fd)


LAYOUTS = {
    "touching": np.array([[-8, 0, 8, 16], [8, 0, 8, 16]], np.float32),
    "overlapping": np.array([[-3, 0, 8, 16], [3, 0, 10, 16]], np.float32),
    "on the border": np.array([[32, 0, 8, 16], [0, -32, 8, 16]], np.float32),
    "partly outside the view": np.array([[40, 0, 8, 20], [-38, 30, 8, 20]], np.float32),
    "1 px small": np.array([[0, 0, 0.5, 1.0], [10, 10, 0.5, 1.0]], np.float32),
    "larger than the frame": np.array([[0, 0, 60, 120], [10, 10, 5, 10]], np.float32),
}


@pytest.fixture(scope="module")
def pair_scene():
    return make_scene(resolution=16, spp=1, n=2)


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_extreme_layouts(pair_scene, name):
    image, _, labels = check_render(pair_scene, LAYOUTS[name], MID)
    if name == "larger than the frame":
        assert (labels == 1).mean() > 0.9  # the big particle fills the view
    if name == "touching":
        assert {1, 2} <= set(np.unique(labels))


@pytest.mark.parametrize("n", [1, 200])
def test_particle_count_extremes(n):
    scene = make_scene(resolution=16, spp=1, n=n)
    rng = np.random.default_rng(n)
    phi = np.zeros((n, 4), np.float32)
    phi[:, :2] = rng.uniform(-32, 32, (n, 2))
    phi[:, 3] = rng.uniform(3, 10, n)
    phi[:, 2] = phi[:, 3] / 2
    _, _, labels = check_render(scene, phi, MID)
    assert labels.max() <= n


def test_spp_one(scene):
    check_render(scene, TINY_PHI, MID, spp=1)


@pytest.mark.parametrize("saturate", [-50.0, 50.0])
def test_saturated_fcn_outputs_stay_finite(saturate):
    torch.manual_seed(0)
    generator = Generator(make_scene(resolution=16, spp=1), hidden=128, blocks=4, dropout=0.1)
    last = generator.regressor.net[-2]
    with torch.no_grad():
        last.bias.fill_(saturate)  # sigmoid -> 0 or 1: every parameter at a limit, sigma included
    phi = torch.from_numpy(TINY_PHI)[None]
    values = generator.learned_values(phi)
    ends = torch.tensor([p.low if saturate < 0 else p.high for p in generator.learned])
    torch.testing.assert_close(values[0], ends, rtol=1e-4, atol=1e-6)
    image = generator(phi)
    image.mean().backward()
    assert torch.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
    assert all(torch.isfinite(p.grad).all() for p in generator.regressor.parameters() if p.grad is not None)


@pytest.mark.parametrize("sigma", [0.001, 0.1])
def test_noise_sigma_at_its_limits(sigma):
    from drgan.models.generator import add_noise

    image = torch.linspace(0, 1, 64).reshape(8, 8)
    s = torch.tensor(sigma, requires_grad=True)
    noisy = add_noise(image, s)
    noisy.sum().backward()
    assert noisy.min() >= 0 and noisy.max() <= 1 and torch.isfinite(s.grad)
