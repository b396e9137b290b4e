"""The generator: FCN -> learned parameters -> render -> noise, batches, and gradients to the FCN."""

import numpy as np
import pytest
import torch
from conftest import TINY_PHI, make_scene

from drgan.models.generator import Generator, add_noise


@pytest.fixture(scope="module")
def generator():
    torch.manual_seed(0)
    return Generator(make_scene(resolution=16, spp=1), hidden=128, blocks=4, dropout=0.1, seed=3)


def test_output_shape_range_and_batches(generator):
    phi = torch.from_numpy(np.stack([TINY_PHI, TINY_PHI + np.float32([3, -2, 0, 0])]))
    images = generator(phi)
    assert images.shape == (2, 1, 16, 16)
    assert torch.isfinite(images).all() and images.min() >= 0 and images.max() <= 1


def test_learned_values_stay_within_limits(generator):
    phi = torch.from_numpy(TINY_PHI)[None] * torch.linspace(0.1, 10, 7)[:, None, None]
    values = generator.learned_values(phi)
    low = torch.tensor([p.low for p in generator.learned])
    high = torch.tensor([p.high for p in generator.learned])
    assert ((values >= low) & (values <= high)).all()
    assert [p.key for p in generator.learned][-1] == "noise.sigma"


def test_gradients_reach_every_fcn_layer(generator):
    generator.zero_grad()
    generator.train()
    phi = torch.from_numpy(np.stack([TINY_PHI, TINY_PHI[::-1].copy()]))
    generator(phi).mean().backward()
    grads = [p.grad for p in generator.regressor.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_batched_backward_equals_per_sample_backward():
    """Two renders before one backward must give the sum of their separate gradients."""
    scene = make_scene(resolution=16, spp=4)
    values = torch.tensor([0.2, 0.5, 0.8, 0.3, 0.4, 0.6])
    layouts = [TINY_PHI, TINY_PHI + np.float32([6, 0, 0, 0])]

    def loss(phi, seed, x):
        scene.set_layout(phi)
        return scene.render(x, seed=seed).square().sum()

    separate = torch.zeros(6)
    for seed, phi in enumerate(layouts):
        x = values.clone().requires_grad_(True)
        loss(phi, seed, x).backward()
        separate += x.grad
    x = values.clone().requires_grad_(True)
    (loss(layouts[0], 0, x) + loss(layouts[1], 1, x)).backward()
    torch.testing.assert_close(x.grad, separate, rtol=1e-4, atol=1e-6)


def test_noise_gradient_matches_finite_differences():
    image = torch.rand(8, 8, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.25
    sigma = torch.tensor(0.05, requires_grad=True)

    def f(s):
        torch.manual_seed(7)
        return add_noise(image, s).sum()

    f(sigma).backward()
    h = 1e-3
    fd = (f(torch.tensor(0.05 + h)) - f(torch.tensor(0.05 - h))) / (2 * h)
    assert sigma.grad == pytest.approx(float(fd), rel=1e-3)


def test_saturated_pixels_still_pass_gradients():
    image = torch.tensor([[0.5, 3.0], [-0.2, 1.0]], requires_grad=True)
    out = add_noise(image, torch.tensor(0.0))
    assert out.min() >= 0 and out.max() <= 1
    out.sum().backward()
    torch.testing.assert_close(image.grad, torch.ones(2, 2))  # straight through, also where clamped


@pytest.mark.parametrize("sigma", [0.001, 0.1, 1.0])
def test_noise_keeps_images_in_range(sigma):
    image = torch.tensor([[0.0, 1.0], [0.5, 2.0]])
    noisy = add_noise(image, torch.tensor(sigma))
    assert noisy.min() >= 0 and noisy.max() <= 1


def test_sample_returns_labels_and_parameters(generator):
    sample = generator.sample(TINY_PHI, seed=5)
    assert sample.image.shape == sample.labels.shape == (16, 16)
    assert set(np.unique(sample.labels)) <= set(range(5)) and sample.labels.max() > 0
    assert set(sample.parameters) >= {"particle.roughness", "stage.base_color", "noise.sigma"}


def test_a_seed_fixes_the_whole_image(generator):
    """Paths and noise both follow the seed (FID images and DDP shares depend on it); the global RNG does not."""
    torch.manual_seed(0)
    first = generator.sample(TINY_PHI, seed=11).image
    torch.manual_seed(1)
    again = generator.sample(TINY_PHI, seed=11).image
    np.testing.assert_array_equal(first, again)
    assert np.abs(generator.sample(TINY_PHI, seed=12).image - first).max() > 0


def test_seeds_change_between_renders(generator):
    first, second = generator.next_seed(), generator.next_seed()
    assert first != second


def test_sample_spp_override_renders_with_less_noise_than_training_spp():
    scene = make_scene(resolution=32, spp=1, sigma={"value": 0.001})
    gen = Generator(scene, hidden=128, blocks=4, dropout=0.1, seed=0)
    noise = {}
    for spp in (None, 64):
        a, b = (gen.sample(TINY_PHI, seed=s, spp=spp).image for s in (1, 2))
        noise[spp] = float(np.std(a - b))
    assert noise[64] < 0.4 * noise[None]  # 1 -> 64 spp: ~8x less Monte Carlo noise
    assert scene.spec.render.spp == 1  # the override does not change the scene


def test_fid_callback_refuses_a_bad_spp():
    from drgan.callbacks import FIDCallback
    from drgan.core.errors import ConfigError

    with pytest.raises(ConfigError, match="callbacks.fid.spp"):
        FIDCallback(spp=10)


# --- real background texture on the stage -----------------------------------------------------------------


def striped_backgrounds(size: int, k: int = 3) -> np.ndarray:
    """Grey level + slow ramp + fine stripes: the high-pass keeps the stripes only."""
    rows = np.arange(size, dtype=np.float32)[:, None]
    ramp = 0.002 * rows * np.ones((1, size), np.float32)
    stripes = 0.05 * np.where(np.arange(size) % 2 == 0, 1.0, -1.0).astype(np.float32)[None, :]
    return np.stack([0.1 + 0.05 * i + ramp + stripes for i in range(k)])


def test_background_texture_keeps_the_fine_structure_only():
    from drgan.models.generator import BackgroundTexture

    texture = BackgroundTexture(striped_backgrounds(32), highpass_px=4.0)
    inner = texture.textures[:, 8:-8, 8:-8]  # away from the border, where the blur reflects
    assert np.abs(inner.mean()) < 1e-3  # grey level and ramp are gone
    np.testing.assert_allclose(np.abs(inner), 0.05, atol=0.005)  # the stripes stay
    first = texture.for_seed(7)
    np.testing.assert_array_equal(first.numpy(), texture.for_seed(7).numpy())  # a seed fixes patch and symmetry
    assert any(not torch.equal(first, texture.for_seed(s)) for s in range(8, 16))


@pytest.mark.parametrize(
    "patches, highpass, match",
    [
        (np.zeros((0, 16, 16)), 8, r"expected square background patches \(k, H, H\) with k >= 1"),
        (np.zeros((2, 16, 12)), 8, "expected square background patches"),
        (np.full((1, 16, 16), np.nan), 8, "non-finite"),
        (np.zeros((1, 16, 16)), 0, "highpass_px=0: expected a number of px > 0"),
    ],
)
def test_bad_background_textures_are_refused(patches, highpass, match):
    from drgan.core.errors import ConfigError
    from drgan.models.generator import BackgroundTexture

    with pytest.raises(ConfigError, match=match):
        BackgroundTexture(patches, highpass_px=highpass)


def test_background_texture_changes_stage_pixels_only_and_no_gradient(one_render_thread):
    from drgan.core.errors import ConfigError
    from drgan.models.generator import BackgroundTexture

    scene = make_scene(resolution=32, spp=4, sigma={"value": 0.001})
    gen = Generator(scene, hidden=128, blocks=4, dropout=0.1, seed=0).eval()
    texture = BackgroundTexture(striped_backgrounds(32), highpass_px=4.0)
    phi = torch.as_tensor(TINY_PHI).unsqueeze(0)

    def image_and_grad():
        gen.zero_grad()
        image = gen.render_one(phi[0], gen.learned_values(phi)[0], seed=5)
        image.sum().backward()
        return image.detach()[0].numpy(), [p.grad.clone() for p in gen.regressor.parameters()]

    plain, plain_grad = image_and_grad()
    gen.set_background(texture)
    textured, textured_grad = image_and_grad()
    stage = scene.instance_labels() == 0
    assert stage.any() and (~stage).any()
    np.testing.assert_array_equal(textured[~stage], plain[~stage])
    expected = np.clip(plain + texture.for_seed(5).numpy(), 0, 1)  # noise is seeded: same on both sides
    inside = stage & (plain > 0.06) & (plain < 0.94)  # away from the clamp
    np.testing.assert_allclose(textured[inside], expected[inside], atol=2e-3)
    for a, b in zip(plain_grad, textured_grad):  # a constant on the image: the same gradient, bit for bit
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(ConfigError, match="background patches of 16 px, renders of 32 px"):
        gen.set_background(BackgroundTexture(striped_backgrounds(16)))
