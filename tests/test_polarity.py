"""Polarity: detecting bright or dark particles, and mining both the same way (synthetic images made here)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi
from test_data import SHAPE, SIZE, STRIDE, disc_image, lattice_centres

from drgan.core.errors import ConfigError, DataError
from drgan.data import mine_patches
from drgan.data.classical import NoParticles
from drgan.data.datamodule import RealPatchDataModule
from drgan.data.polarity import detect_polarity, image_vote, isophote_convexity, resolve_polarity, to_bright


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


def disc_field(coverage, seed, radius=10, shape=(192, 224), noise=0.03, grain=0.0, disc=0.7, back=0.2):
    """Discs of radius 10 px (+-15 %) dropped at random until they cover ``coverage`` of the image, each
    overlapping the ones before by at most 10 % of its area (dense fields: touching discs and clusters); grey
    ``disc`` on ``back``, plus noise of std ``noise`` (smoothed over ``grain`` px when given)."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    mask = np.zeros(shape, bool)
    while mask.mean() < coverage:
        cy, cx, r = rng.uniform(0, shape[0]), rng.uniform(0, shape[1]), radius * rng.uniform(0.85, 1.15)
        new = (rr - cy) ** 2 + (cc - cx) ** 2 <= r**2
        if (new & mask).sum() <= 0.1 * new.sum():
            mask |= new
    grainy = rng.normal(0, 1, shape)
    if grain:
        grainy = ndi.gaussian_filter(grainy, grain)
        grainy /= grainy.std()
    return np.clip(np.where(mask, disc, back) + noise * grainy, 0, 1).astype(np.float32), mask


@pytest.mark.parametrize("seed", [0, 1])
def test_a_dense_field_of_touching_particles_is_read_the_right_way_round(seed):
    """Discs on ~60 % of the image: the most frequent grey is the particles', so the histogram-mode vote alone
    reads the field backwards; the particles' convex outlines give it away, in either polarity."""
    image, mask = disc_field(0.6, seed)
    assert 0.58 < mask.mean() < 0.65
    image[170:176, 12:72] = 1.0  # a scale bar: an annotation, not a particle
    vote = image_vote(image)
    assert vote.mode_vote == "dark"  # the vote before: backwards
    assert vote.polarity == "bright" and vote.convexity > 0.2
    # the background's grey (0.2, smoothed into the narrow gaps), not the mode's (the discs')
    assert vote.background < 0.3 < 0.6 < vote.mode
    assert detect_polarity([image]).polarity == "bright"
    negative = dark_twin(image)
    assert image_vote(negative).mode_vote == "bright"
    assert detect_polarity([negative]).polarity == "dark"
    assert detect_polarity([negative, negative[::-1]]).as_dict()["mode_vote_disagrees"] == 2


def test_a_sparse_field_keeps_its_polarity_and_both_cues_agree():
    image, mask = disc_field(0.15, seed=2)
    vote = image_vote(image)
    assert (vote.polarity, vote.mode_vote) == ("bright", "bright") and vote.convexity > 0.4
    assert image_vote(dark_twin(image)).polarity == "dark"


def test_grainy_noisy_dark_particles_read_dark():
    """TEM-like: dark discs (0.35) on a bright film (0.75), noise of std 0.12 with a grain of 1.5 px."""
    image, mask = disc_field(0.3, seed=3, noise=0.12, grain=1.5, disc=0.35, back=0.75)
    vote = image_vote(image)
    assert vote.polarity == "dark" and vote.convexity < -0.2
    assert detect_polarity([image, image.T.copy()]).polarity == "dark"


def test_the_convexity_is_odd_in_the_grey_and_unbiased_on_noise():
    """Negating an image negates its convexity exactly; pure noise has no convex side on average."""
    noises = [np.random.default_rng(seed).normal(0.5, 0.1, (256, 256)) for seed in range(4)]
    values = [isophote_convexity(noise) for noise in noises]
    assert isophote_convexity(1 - noises[0]) == pytest.approx(-values[0], abs=1e-9)
    assert abs(np.mean(values)) < 0.05 and max(map(abs, values)) < 0.15


def test_a_flat_image_or_a_tie_asks_for_the_setting(field):
    image, _ = field
    with pytest.raises(DataError, match="data.polarity"):
        detect_polarity([np.full((32, 32), 0.4, np.float32)])
    flat = image_vote(np.full((64, 64), 0.4, np.float32))
    assert flat.polarity is None and flat.margin == 0
    with pytest.raises(DataError, match="data.polarity=bright or data.polarity=dark"):
        detect_polarity([image, dark_twin(image)])
    with pytest.raises(ConfigError, match="data.polarity='grey'"):
        resolve_polarity("grey", [image])
    assert resolve_polarity("dark", [image]) == ("dark", None)  # an explicit setting is not second-guessed


def test_dark_particles_mine_the_same_patches_as_their_bright_twin(field):
    image, mask = field
    ids = ["a"]
    bright = mine_patches([image], ids, size=SIZE, stride=STRIDE, min_particles=2, n_background=3, progress=False)
    dark = mine_patches(
        [dark_twin(image)],
        ids,
        size=SIZE,
        stride=STRIDE,
        min_particles=2,
        n_background=3,
        polarity="dark",
        progress=False,
    )
    assert len(bright.train) > 0
    np.testing.assert_array_equal(dark.train_positions, bright.train_positions)
    np.testing.assert_array_equal(dark.train_counts, bright.train_counts)
    np.testing.assert_array_equal(dark.background_positions, bright.background_positions)
    # the patches keep the image's own values: dark particles stay dark
    r, c = dark.train_positions[0]
    np.testing.assert_array_equal(dark.train[0], dark_twin(image)[r : r + SIZE, c : c + SIZE])
    # mined with the wrong polarity, the bright background is taken for particles (its round holes, the real
    # particles, filled as their centres): either nothing of plausible size is found and the error names the
    # polarity key, or no window is free of "particles" and none is taken as background; never windows full of them
    try:
        wrong = mine_patches(
            [dark_twin(image)], ids, size=SIZE, stride=STRIDE, min_particles=2, n_background=3, progress=False
        )
    except NoParticles as error:
        assert "data.polarity" in str(error)
    else:
        assert len(wrong.background) == 0 and wrong.params["background_report"]["found"] == 0


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
    dm = RealPatchDataModule(
        str(folder),
        split=None,
        crop_rows=None,
        patch_size=SIZE,
        stride=STRIDE,
        min_particles=2,
        n_background=2,
        cache_dir=str(tmp_path / "patches"),
    )
    dm.setup()
    assert dm.polarity == "dark" and dm.polarity_estimate["dark_votes"] == 3
    assert dm.patches.params["polarity"] == "dark"
    # the cache remembers the detected polarity
    again = RealPatchDataModule(
        str(folder),
        split=None,
        crop_rows=None,
        patch_size=SIZE,
        stride=STRIDE,
        min_particles=2,
        n_background=2,
        cache_dir=str(tmp_path / "patches"),
    )
    again.setup()
    assert again.polarity == "dark"


def test_an_unset_data_dir_says_how_to_set_it():
    with pytest.raises(ConfigError, match="data.dir is not set.*drgan.profile"):
        RealPatchDataModule(None)


# --- a material knows its data ------------------------------------------------------------------------------


def write_field(folder, image, n=2):
    import tifffile

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        tifffile.imwrite(folder / f"f{k}.tif", (np.roll(image, 16 * k, axis=1) * 255).astype(np.uint8))
    return folder


def train_overrides(folder, tmp_path, *extra):
    from test_train import tiny_overrides

    return [o for o in tiny_overrides(folder, tmp_path / "run") if not o.startswith("data.check_material")] + list(
        extra
    )


@pytest.fixture
def no_mining(monkeypatch):
    import drgan.data.datamodule as dm

    monkeypatch.setattr(
        dm, "mine_patches", lambda *a, **k: pytest.fail("patches mined before the material was checked")
    )


def test_a_bright_particle_material_is_refused_on_dark_particle_images(tmp_path, field, no_mining):
    from test_train import run_train

    folder = write_field(tmp_path / "tsem", dark_twin(field[0]))
    with pytest.raises(ConfigError) as caught:
        run_train(train_overrides(folder, tmp_path, "material.particle_size_px=12"))
    message = str(caught.value)
    assert "material=tio2_sem is made for bright particles" in message and "are darker than their background" in message
    assert "material=tio2_tsem" in message and "drgan.profile" in message and "data.check_material=false" in message


def test_a_material_whose_particles_are_over_twice_the_datas_is_refused(tmp_path, field, no_mining):
    from test_train import run_train

    folder = write_field(tmp_path / "sem", field[0])  # discs of 13 px equivalent diameter
    with pytest.raises(
        ConfigError, match=r"particles of 30 px \(material.particle_size_px\).*measure 1[23]\.\d px.*0\.4\dx"
    ):
        run_train(train_overrides(folder, tmp_path))


def test_the_material_check_passes_data_that_fits_and_records_what_it_compared(tmp_path, field):
    import dataclasses

    from conftest import compose

    from drgan.scene.config import typed_material

    folder = write_field(tmp_path / "sem", field[0])
    dm = RealPatchDataModule(str(folder), split=None, crop_rows=None, patch_size=SIZE)
    material = typed_material(compose(["material=tio2_sem"]).material)
    report = dm.check_fits(dataclasses.replace(material, name="m", particle_size_px=14))
    assert report["data_polarity"] == "bright" and 0.8 < report["size_ratio"] < 1.0
    off = RealPatchDataModule(str(folder), split=None, crop_rows=None, patch_size=SIZE, check_material=False)
    assert off.check_fits(dataclasses.replace(material, polarity="dark", particle_size_px=100)) is None
    assert off.polarity == "bright"  # still detected: mining needs it


def test_a_material_without_shipped_images_asks_for_them_before_anything_runs(tmp_path):
    from conftest import compose
    from test_train import run_train

    cfg = compose(["material=sio2_him", "placement=poisson"], config_name="train")
    assert cfg.data.dir is None  # never another material's images by default
    assert compose([], config_name="train").data.dir.endswith("tio2_sem/images")  # the default material's own
    with pytest.raises(
        ConfigError,
        match=r"data.dir is not set: material=sio2_him is made for SiO2 nanoparticles in HIM.*"
        r"material=sio2_him data.dir=/path/to/images",
    ):
        run_train(["material=sio2_him", "placement=poisson", f"paths.output_dir={tmp_path / 'run'}", "logger=none"])
