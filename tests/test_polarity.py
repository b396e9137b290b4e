"""Polarity: detecting bright or dark particles, and mining both the same way (synthetic images made here)."""

from __future__ import annotations

import numpy as np
import pytest

from drgan.data import mine_patches
from drgan.data.datamodule import RealPatchDataModule
from drgan.data.polarity import detect_polarity, image_vote, resolve_polarity, to_bright
from drgan.errors import ConfigError, DataError
from test_data import SHAPE, SIZE, STRIDE, disc_image, lattice_centres


def dark_twin(image):
    """The same field in transmission: dark discs on a bright background (1 - image, plus an offset)."""
    return np.clip(1.05 - image, 0, 1).astype(np.float32)


@pytest.fixture(scope="module")
def field():
    centres = lattice_centres(SHAPE, seed=1, empty=(128, 160))
    image, mask = disc_image(centres, SHAPE, seed=2)
    return image, mask


def test_each_polarity_is_detected_with_full_confidence(field):
    image, _ = field
    bright = detect_polarity([image, image[::-1]])
    dark = detect_polarity([dark_twin(image), dark_twin(image)[:, ::-1]])
    assert (bright.polarity, bright.confidence) == ("bright", 1.0)
    assert (dark.polarity, dark.confidence) == ("dark", 1.0)
    # the vote's background level is the background's grey (0.15 bright case, 0.9 dark case), not the particles'
    assert abs(image_vote(image).mode - 0.15) < 0.05
    assert abs(image_vote(dark_twin(image)).mode - 0.90) < 0.05


def test_polarity_follows_the_background_even_when_particles_cover_much_of_the_image():
    """Particles on 40 % of the image: the background is still the most frequent grey level."""
    centres = lattice_centres(SHAPE, seed=3, p=0.9)
    image, mask = disc_image(centres, SHAPE, seed=4)
    assert 0.3 < mask.mean() < 0.5
    assert detect_polarity([image]).polarity == "bright"
    assert detect_polarity([dark_twin(image)]).polarity == "dark"


def test_a_flat_image_or_a_tie_asks_for_the_setting(field):
    image, _ = field
    with pytest.raises(DataError, match="data.polarity"):
        detect_polarity([np.full((32, 32), 0.4, np.float32)])
    with pytest.raises(DataError, match="data.polarity=bright or data.polarity=dark"):
        detect_polarity([image, dark_twin(image)])
    with pytest.raises(ConfigError, match="data.polarity='grey'"):
        resolve_polarity("grey", [image])
    assert resolve_polarity("dark", [image]) == ("dark", None)  # an explicit setting is not second-guessed


def test_dark_particles_mine_the_same_patches_as_their_bright_twin(field):
    image, mask = field
    ids = ["a"]
    bright = mine_patches([image], ids, size=SIZE, stride=STRIDE, min_particles=2, n_background=3, progress=False)
    dark = mine_patches([dark_twin(image)], ids, size=SIZE, stride=STRIDE, min_particles=2, n_background=3,
                        polarity="dark", progress=False)
    assert len(bright.train) > 0
    np.testing.assert_array_equal(dark.train_positions, bright.train_positions)
    np.testing.assert_array_equal(dark.train_counts, bright.train_counts)
    np.testing.assert_array_equal(dark.background_positions, bright.background_positions)
    assert np.all(dark.background_fractions == 0)
    # the patches keep the image's own values: dark particles stay dark
    r, c = dark.train_positions[0]
    np.testing.assert_array_equal(dark.train[0], dark_twin(image)[r : r + SIZE, c : c + SIZE])
    # mined with the wrong polarity, the bright background is taken for particles: no clean background
    wrong = mine_patches([dark_twin(image)], ids, size=SIZE, stride=STRIDE, min_particles=2, n_background=3,
                         progress=False)
    assert wrong.background_fractions.min() > 0.5


def test_to_bright_is_the_negative_for_dark_particles():
    x = np.array([[0.0, 0.25], [0.5, 1.0]], np.float32)
    np.testing.assert_array_equal(to_bright(x, "bright"), x)
    np.testing.assert_array_equal(to_bright(x, "dark"), 1 - x)


def test_the_datamodule_detects_and_records_dark_particles(tmp_path, field):
    import tifffile

    image, _ = field
    folder = tmp_path / "images"
    folder.mkdir()
    for k in range(3):
        tifffile.imwrite(folder / f"f{k}.tif", (dark_twin(np.roll(image, 16 * k, axis=1)) * 255).astype(np.uint8))
    dm = RealPatchDataModule(str(folder), split=None, crop_rows=None, patch_size=SIZE, stride=STRIDE, min_particles=2,
                             n_background=2, cache_dir=str(tmp_path / "patches"))
    dm.setup()
    assert dm.polarity == "dark" and dm.polarity_estimate["dark_votes"] == 3
    assert dm.patches.params["polarity"] == "dark"
    assert np.all(dm.patches.background_fractions == 0)
    # the cache remembers the detected polarity
    again = RealPatchDataModule(str(folder), split=None, crop_rows=None, patch_size=SIZE, stride=STRIDE,
                                min_particles=2, n_background=2, cache_dir=str(tmp_path / "patches"))
    again.setup()
    assert again.polarity == "dark"


def test_an_unset_data_dir_says_how_to_set_it():
    with pytest.raises(ConfigError, match="data.dir is not set.*drgan.profile"):
        RealPatchDataModule(None)
