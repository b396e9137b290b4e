"""drgan.segmenters.noise_match: the noise level estimator, matching up to a level (never down), repeatable, and
inference bringing a clean image up to the model's stored level before the network sees it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drgan.core.errors import ConfigError
from drgan.segmenters import noise_match as nm


def _discs(size: int = 128, sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), 0.3)
    for cy, cx in ((40, 40), (88, 80)):
        image[np.hypot(yy - cy, xx - cx) <= 18] = 0.7
    return (image + np.random.default_rng(seed).normal(0, sigma, image.shape)).astype(np.float32)


def test_the_level_reads_white_noise_through_its_edges_and_is_linear_in_it():
    assert nm.noise_level(_discs()) == pytest.approx(0.0, abs=1e-6)  # the outlines alone: no noise read
    gain = nm.white_gain()
    assert 0.5 < gain < 1.0  # the blur subtracted keeps part of white noise
    for sigma in (0.01, 0.04):
        assert nm.noise_level(_discs(sigma=sigma, seed=1)) == pytest.approx(gain * sigma, rel=0.1)  # edges: a few %


def test_matching_brings_a_clean_image_up_to_the_level_and_never_down():
    clean = _discs(sigma=0.01, seed=2)
    target = nm.noise_level(_discs(sigma=0.04, seed=3))
    matched = nm.match_noise(clean, target)
    assert nm.noise_level(matched) == pytest.approx(target, rel=0.06)  # levels add in quadrature
    np.testing.assert_array_equal(matched, nm.match_noise(clean, target))  # repeatable
    noisy = _discs(sigma=0.05, seed=4)
    assert nm.match_noise(noisy, target) is noisy  # as noisy already: untouched
    assert nm.match_noise(clean, None) is clean and nm.match_noise(clean, 0.0) is clean
    assert nm.added_sigma(0.03, 0.03) == 0.0 and nm.added_sigma(0.0, nm.white_gain() * 0.02) == pytest.approx(0.02)
    assert nm.stored_level({nm.NOISE_KEY: 0.02}) == 0.02
    assert nm.stored_level({}) is None and nm.stored_level({nm.NOISE_KEY: "x"}) is None


class _Spy(torch.nn.Module):
    """Records the noise level of every tile it is given; answers background everywhere."""

    def __init__(self):
        super().__init__()
        self.levels: list[float] = []

    def forward(self, x):
        self.levels += [nm.noise_level(t[0].numpy()) for t in x]
        return torch.cat([torch.ones_like(x), torch.zeros_like(x), torch.zeros_like(x)], 1)


def test_inference_matches_the_models_level_unless_told_otherwise():
    from drgan.segmenters.inference import make_predictor

    image = _discs(sigma=0.005, seed=5)
    model = _Spy()
    model.train_noise = 0.03  # as load_segmenter sets it from the checkpoint
    make_predictor(model, {"tile": 128})(image)
    assert model.levels[-1] == pytest.approx(0.03, rel=0.08)
    make_predictor(model, {"tile": 128, "noise_match": False})(image)  # off
    assert model.levels[-1] == pytest.approx(nm.noise_level(image), rel=1e-3)
    make_predictor(model, {"tile": 128, "noise_match": 0.02})(image)  # a level given overrides the model's
    assert model.levels[-1] == pytest.approx(0.02, rel=0.08)
    model.train_noise = None  # a real-trained segmenter stores none: nothing added
    make_predictor(model, {"tile": 128})(image)
    assert model.levels[-1] == pytest.approx(nm.noise_level(image), rel=1e-3)
    with pytest.raises(ConfigError, match="noise_match"):
        make_predictor(model, {"noise_match": 3})
