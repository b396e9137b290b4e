"""Reading real images, splits, and patch mining, on synthetic images made here."""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.data import (
    PatchSet,
    SegmentParams,
    contact_sheet,
    count_particles,
    dihedral_augment,
    list_images,
    mine_patches,
    read_grey,
    read_split,
)

# --- synthetic particles -----------------------------------------------------------------------------------

RADIUS = 6
SIZE, STRIDE = 64, 32  # windows start at multiples of 32 when (H - 64) and (W - 64) are multiples of 32


def disc_image(centres, shape, seed=0, noise=0.02):
    """Bright discs (0.7) of RADIUS on a dark noisy background (0.15); returns (image, disc mask)."""
    rr, cc = np.mgrid[: shape[0], : shape[1]]
    mask = np.zeros(shape, bool)
    for cy, cx in centres:
        mask |= (rr - cy) ** 2 + (cc - cx) ** 2 <= RADIUS**2
    rng = np.random.default_rng(seed)
    image = np.where(mask, 0.7, 0.15) + rng.normal(0, noise, shape)
    return np.clip(image, 0, 1).astype(np.float32), mask


def lattice_centres(shape, seed=0, p=0.35, empty=None):
    """Disc centres on a 16-px lattice (0 and 16 mod 32): a disc either lies well inside a window or
    crosses its edge by >= 6 px, never ambiguously close; centres on row or column 0 touch the border."""
    rng = np.random.default_rng(seed)
    centres = []
    for cy in range(0, shape[0], 16):
        for cx in range(0, shape[1], 16):
            if empty is not None and empty[0] <= cy and empty[1] <= cx:
                continue
            if rng.random() < p:
                centres.append((cy, cx))
    return centres


def true_full_count(centres, row, col, size=SIZE):
    """Discs whose every pixel lies inside the window and off its edge rows and columns."""
    return sum(
        row < cy - RADIUS and cy + RADIUS < row + size - 1 and col < cx - RADIUS and cx + RADIUS < col + size - 1
        for cy, cx in centres
    )


SHAPE = (224, 288)


@pytest.fixture(scope="module")
def synthetic():
    centres = lattice_centres(SHAPE, seed=1, empty=(128, 160))
    image, mask = disc_image(centres, SHAPE, seed=2)
    return image, mask, centres


# --- counting and selection ---------------------------------------------------------------------------------


def test_count_particles_exact_on_clean_patch():
    inside = [(20, 20), (20, 60), (50, 35), (75, 75)]
    cut = [(0, 40), (40, 95), (95, 10)]  # centred on the border rows / columns of a 96 x 96 patch
    touching = [(70, 20), (70, 33)]  # two overlapping discs: an agglomerate the watershed must split
    patch, _ = disc_image(inside + cut + touching, (96, 96), seed=3)
    assert count_particles(patch) == len(inside) + len(touching)


def test_count_particles_finds_none_in_noise():
    rng = np.random.default_rng(4)
    assert count_particles(np.clip(rng.normal(0.2, 0.05, (96, 96)), 0, 1).astype(np.float32)) == 0


def test_mined_counts_match_truth_and_selection_keeps_three_or_more(synthetic):
    image, _, centres = synthetic
    ps = mine_patches(
        [image], ["syn"], size=SIZE, stride=STRIDE, min_particles=3, n_background=0, max_overlap=0.99, progress=False
    )
    truth = {
        (r, c): true_full_count(centres, r, c)
        for r in range(0, SHAPE[0] - SIZE + 1, STRIDE)
        for c in range(0, SHAPE[1] - SIZE + 1, STRIDE)
    }
    kept = {tuple(p) for p in ps.train_positions}
    assert kept, "no patch selected"
    for (r, c), count in zip(ps.train_positions, ps.train_counts):
        assert count == truth[(r, c)]
    # Every window with >= 3 particles is kept (no two are duplicates at max_overlap 0.99), and no other.
    assert kept == {w for w, n in truth.items() if n >= 3}
    assert any(0 < n < 3 for n in truth.values()), "the synthetic image should also hold rejectable windows"
    patch_of = {tuple(p): t for p, t in zip(ps.train_positions, ps.train)}
    r, c = next(iter(kept))
    np.testing.assert_array_equal(patch_of[(r, c)], image[r : r + SIZE, c : c + SIZE])


def test_the_scale_search_names_the_settings_that_mine_alike_without_it(synthetic, caplog):
    """The search (minutes per image on real micrographs) logs the overrides that skip it; mined with them, the same
    patches and the same resolved settings come out, and nothing is searched."""
    image, _, _ = synthetic
    with caplog.at_level(logging.INFO, logger="drgan.data.patches"):
        searched = mine_patches([image], ["syn"], size=SIZE, stride=STRIDE, n_background=2, progress=False)
    assert "searching the particle scale on 1 of the 1 images" in caplog.text
    overrides = dict(
        re.findall(r"data\.segment\.(\w+)=(\S+)", caplog.text.split("mine alike without the search with")[1])
    )
    assert set(overrides) >= {"scale", "neck_depth"} and float(overrides["scale"]) > 0
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="drgan.data.patches"):
        pinned = mine_patches(
            [image], ["syn"], size=SIZE, stride=STRIDE, n_background=2, progress=False,
            segment=SegmentParams(**{key: float(value) for key, value in overrides.items()}),
        )  # fmt: skip
    assert "searching" not in caplog.text and "mine alike" not in caplog.text
    assert pinned.params["segment"] == searched.params["segment"]
    np.testing.assert_array_equal(pinned.train_positions, searched.train_positions)
    np.testing.assert_array_equal(pinned.background_positions, searched.background_positions)


def test_overlapping_windows_are_dropped(synthetic):
    image, _, _ = synthetic
    ps = mine_patches([image], ["syn"], size=SIZE, stride=STRIDE, n_background=0, max_overlap=0.0, progress=False)
    positions = ps.train_positions
    for i in range(len(positions)):
        for j in range(i + 1, len(positions)):
            assert np.any(np.abs(positions[i] - positions[j]) >= SIZE), "kept windows overlap"


def test_near_duplicate_images_are_dropped(synthetic):
    image, _, centres = synthetic
    again, _ = disc_image(centres, SHAPE, seed=99, noise=0.005)  # the same scene, imaged again
    one = mine_patches([image], ["a"], size=SIZE, stride=STRIDE, n_background=0, progress=False)
    two = mine_patches([image, again], ["a", "b"], size=SIZE, stride=STRIDE, n_background=0, progress=False)
    assert len(two.train) == len(one.train) > 0
    assert set(two.train_ids) == {"a"}


def test_background_patches_hold_no_particle(synthetic, caplog):
    image, mask, _ = synthetic
    ps = mine_patches([image], ["syn"], size=SIZE, stride=STRIDE, n_background=3, progress=False)
    assert len(ps.background) == 3
    for r, c in ps.background_positions:
        assert not mask[r : r + SIZE, c : c + SIZE].any()
    # Asking for more than exist: only particle-free windows are taken (fewer than asked), and the shortfall is said.
    with caplog.at_level(logging.WARNING, logger="drgan.data.patches"):
        many = mine_patches([image], ["syn"], size=SIZE, stride=STRIDE, n_background=40, progress=False)
    report = many.params["background_report"]
    assert report["found"] == len(many.background) < 40 and report["max_foreground_fraction"] == 0.0
    for r, c in many.background_positions:
        assert not mask[r : r + SIZE, c : c + SIZE].any()
    assert "free of particles" in caplog.text
    # A field covered with particles has no background window: none is taken, and that is no error.
    full = mine_patches([image[:, : SIZE + 8]], ["full"], size=SIZE, n_background=5, progress=False)
    assert full.params["background_report"]["found"] == len(full.background) == 0 or not any(
        mask[r : r + SIZE, c : c + SIZE].any() for r, c in full.background_positions
    )


def test_image_smaller_than_patch_names_image():
    small = np.zeros((100, 300), np.float32)
    with pytest.raises(DataError, match=r"'tiny'.*300 x 100"):
        mine_patches([small], ["tiny"], size=256, progress=False)


def test_dihedral_augment_gives_eight_distinct_views_with_same_content():
    patch = np.random.default_rng(5).random((6, 6)).astype(np.float32)
    views = [dihedral_augment(patch, k) for k in range(8)]
    assert len({v.tobytes() for v in views}) == 8
    for v in views:
        np.testing.assert_array_equal(np.sort(v, axis=None), np.sort(patch, axis=None))
    np.testing.assert_array_equal(views[0], patch)
    np.testing.assert_array_equal(views[1], np.rot90(patch))
    assert any(np.array_equal(v, patch.T) for v in views)
    batch = np.stack([patch, patch + 1])
    np.testing.assert_array_equal(dihedral_augment(batch, 5)[1], views[5] + 1)
    with pytest.raises(ConfigError):
        dihedral_augment(patch, 8)


def test_patchset_save_load_and_contact_sheet(synthetic, tmp_path):
    image, _, _ = synthetic
    ps = mine_patches([image], ["syn"], size=SIZE, stride=STRIDE, n_background=2, progress=False)
    ps.save(tmp_path / "set")
    back = PatchSet.load(tmp_path / "set")
    np.testing.assert_array_equal(back.train, ps.train)
    np.testing.assert_array_equal(back.background_positions, ps.background_positions)
    assert back.train_ids == ps.train_ids and back.summary() == ps.summary()
    assert ps.summary()["n_train"] == len(ps.train) and ps.summary()["n_background"] == 2
    assert not list((tmp_path / "set").glob("*.tmp"))
    sheet = contact_sheet(ps, tmp_path / "sheet.png", title="synthetic")
    assert Image.open(sheet).size[0] > 0
    with pytest.raises(DataError, match="patches.npz"):
        PatchSet.load(tmp_path)
    # a cache written when patches.npz still carried background_fractions (all 0) loads as before
    with np.load(tmp_path / "set" / "patches.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    np.savez_compressed(tmp_path / "set" / "patches.npz", **arrays, background_fractions=np.zeros(2))
    old = PatchSet.load(tmp_path / "set")
    np.testing.assert_array_equal(old.background, ps.background)
    assert old.summary() == ps.summary()


# --- reading ------------------------------------------------------------------------------------------------

GREY = np.arange(0, 240, dtype=np.uint8).reshape(12, 20)


def test_read_8bit_grey_png(tmp_path):
    Image.fromarray(GREY).save(tmp_path / "a.png")
    g = read_grey(tmp_path / "a.png")
    assert g.dtype == np.float32 and g.shape == GREY.shape
    np.testing.assert_allclose(g, GREY / 255, atol=1e-6)


def test_read_16bit_tiff_and_png(tmp_path):
    data = (np.arange(240, dtype=np.uint16).reshape(12, 20) * 273).astype(np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", data)
    np.testing.assert_allclose(read_grey(tmp_path / "a.tif"), data / 65535, atol=1e-6)
    Image.fromarray(data).save(tmp_path / "b.png")
    np.testing.assert_allclose(read_grey(tmp_path / "b.png"), data / 65535, atol=1e-6)


def test_read_palette_tiff_and_png_maps_through_palette(tmp_path):
    index = (GREY % 4).astype(np.uint8)
    colormap = np.zeros((3, 256), np.uint16)
    colormap[:, :4] = np.array([[65535, 0, 0], [0, 65535, 0], [0, 0, 65535], [65535, 65535, 65535]]).T
    tifffile.imwrite(tmp_path / "p.tif", index, photometric="palette", colormap=colormap)
    luma = np.array([0.299, 0.587, 0.114, 1.0])
    np.testing.assert_allclose(read_grey(tmp_path / "p.tif"), luma[index], atol=1e-6)
    img = Image.fromarray(index, mode="P")
    img.putpalette([255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255])
    img.save(tmp_path / "p.png")
    np.testing.assert_allclose(read_grey(tmp_path / "p.png"), luma[index], atol=1e-6)


def test_read_rgb_jpeg_and_rgba_png_to_luminance(tmp_path):
    rgb = np.zeros((32, 64, 3), np.uint8)
    rgb[:, :32] = (200, 100, 50)
    rgb[:, 32:] = (10, 220, 90)
    Image.fromarray(rgb).save(tmp_path / "c.jpg", quality=95)
    expected = rgb @ np.array([0.299, 0.587, 0.114]) / 255
    g = read_grey(tmp_path / "c.jpg")
    assert g.shape == (32, 64)
    np.testing.assert_allclose(g[4:-4, 4:28], expected[4:-4, 4:28], atol=0.02)  # JPEG is lossy
    np.testing.assert_allclose(g[4:-4, 36:-4], expected[4:-4, 36:-4], atol=0.02)
    rgba = np.concatenate([rgb, np.full((32, 64, 1), 128, np.uint8)], axis=-1)
    Image.fromarray(rgba).save(tmp_path / "d.png")
    np.testing.assert_allclose(read_grey(tmp_path / "d.png"), expected, atol=1e-6)


def test_float_tiff_must_lie_in_unit_range(tmp_path):
    tifffile.imwrite(tmp_path / "ok.tif", np.full((4, 4), 0.25, np.float32))
    assert read_grey(tmp_path / "ok.tif")[0, 0] == 0.25
    tifffile.imwrite(tmp_path / "counts.tif", np.full((4, 4), 300.0, np.float32))
    with pytest.raises(DataError, match=r"counts\.tif.*\[0, 1\]"):
        read_grey(tmp_path / "counts.tif")


def test_crop_rows_removes_info_bar(tmp_path):
    Image.fromarray(GREY).save(tmp_path / "a.png")
    g = read_grey(tmp_path / "a.png", crop_rows=(9, 12))
    np.testing.assert_allclose(g, GREY[:9] / 255, atol=1e-6)
    with pytest.raises(DataError, match="crop_rows"):
        read_grey(tmp_path / "a.png", crop_rows=(9, 30))


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match="missing.tif"):
        read_grey(tmp_path / "missing.tif")
    (tmp_path / "junk.tif").write_bytes(np.random.default_rng(6).bytes(4096))
    with pytest.raises(DataError, match="junk.tif"):
        read_grey(tmp_path / "junk.tif")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(DataError, match="junk.png"):
        read_grey(tmp_path / "junk.png")
    (tmp_path / "a.bmp").write_bytes(b"")
    with pytest.raises(DataError, match="unsupported file kind"):
        read_grey(tmp_path / "a.bmp")


def test_list_images_by_id(tmp_path):
    with pytest.raises(DataError, match=f"{tmp_path.name}.*no image files"):
        list_images(tmp_path)
    for stem in ("b", "a"):
        Image.fromarray(GREY).save(tmp_path / f"{stem}.png")
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in list_images(tmp_path)] == ["a.png", "b.png"]
    assert [p.name for p in list_images(tmp_path, ["b", "a"])] == ["b.png", "a.png"]
    with pytest.raises(DataError, match="test7"):
        list_images(tmp_path, ["a", "test7"])
    with pytest.raises(DataError, match="no such folder"):
        list_images(tmp_path / "nope")


def test_read_split(tmp_path):
    good = tmp_path / "split.json"
    good.write_text(json.dumps({"train": ["1", "2"], "test": ["3"]}))
    assert read_split(good) == {"train": ["1", "2"], "test": ["3"]}
    bad = tmp_path / "overlap.json"
    bad.write_text(json.dumps({"train": ["1", "2"], "test": ["2"]}))
    with pytest.raises(DataError, match=r"overlap\.json.*'2'"):
        read_split(bad)
    for name, text in (
        ("nojson.json", "{train"),
        ("notest.json", '{"train": ["1"]}'),
        ("ints.json", '{"train": [1], "test": []}'),
    ):
        (tmp_path / name).write_text(text)
        with pytest.raises(DataError, match=name):
            read_split(tmp_path / name)


# --- the real TiO2 SEM data (manual check) -------------------------------------------------------------------

TIO2 = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "tio2_sem"


@pytest.mark.slow
@pytest.mark.skipif(not (TIO2 / "split.json").is_file(), reason=f"TiO2 SEM data not at {TIO2}")
def test_mine_real_tio2_sem(tmp_path, request):
    if "slow" not in (request.config.getoption("markexpr") or ""):
        pytest.skip("manual check on real data: run with `-m slow`")
    ids = read_split(TIO2 / "split.json")["train"]
    start = time.perf_counter()
    images = [read_grey(p, crop_rows=(712, 768)) for p in list_images(TIO2 / "images", ids)]
    ps = mine_patches(images, ids, size=256, stride=288, min_particles=3, n_background=200)
    seconds = time.perf_counter() - start
    contact_sheet(ps, tmp_path / "contact.png", title=f"TiO2 SEM train: stride 288, {seconds:.0f} s")
    summary = ps.summary()
    print(json.dumps({k: v for k, v in summary.items() if k != "train_per_image"}), f"{seconds:.1f} s")
    assert 100 <= summary["n_train"] <= 150  # the paper hand-picked 124
    # Only windows free of particles are backgrounds: fewer than the 200 asked for on these dense fields, none with
    # a particle pixel (the segmentation's foreground)
    assert 100 <= summary["n_background"] <= 200 and summary["background_max_fraction"] == 0.0
    assert set(ps.train_ids) <= set(ids)


@pytest.mark.slow
@pytest.mark.parametrize("experiment", ["tio2_sem", "tio2_tsem"])
def test_the_experiments_set_the_scale_their_train_ids_give(experiment):
    """experiment=tio2_sem / tio2_tsem set data.segment.scale and neck_depth so that training skips the search
    (6-7 min on 2 cores): what the search finds on their train ids, as mining samples them, must be what they set."""
    from hydra.utils import instantiate

    from drgan.launch.configs import compose

    data = TIO2.parent
    if not (data / experiment / "images").is_dir():
        pytest.skip(f"{experiment} not at {data}")
    overrides = [f"experiment={experiment}", "logger=none", "data.cache_dir=null", f"paths.data_dir={data}"]
    cfg = compose(overrides, config_name="train")
    dm = instantiate(cfg.data, resolution=int(cfg.renderer.resolution))
    paths, _, test_ids = dm.resolve_ids()
    assert test_ids and not set(test_ids) & {p.stem for p in paths}
    pinned = SegmentParams.from_config(dm.segment)
    searched, _, ids = dm.search_segment()
    assert ids and not set(ids) & set(test_ids)
    assert (searched.scale, searched.neck_depth, searched.min_separability) == (
        pinned.scale, pinned.neck_depth, pinned.min_separability,
    ), "rerun `python experiments/profile/pin_scale.py` and set what it prints in the experiment"  # fmt: skip


# --- too few patches: refused right after mining ----------------------------------------------------------------


@pytest.mark.parametrize(
    "settings, found, needed",
    [
        ({"min_particles": 2}, "only 1 24 px patch", 2),  # 3 images, 1 patch: no FID covariance
        ({"min_particles": 1, "batch_size": 8}, r"only 5 24 px patch", 8),  # 5 patches, not one batch of 8
        ({"min_particles": 9}, "no 24 px patch", 2),
    ],
)
def test_too_few_patches_fail_at_setup_naming_count_images_and_settings(settings, found, needed, tmp_path):
    from test_train import datamodule, make_images

    folder = make_images(tmp_path / "images", n=3, size=40, seed=2)
    dm = datamodule(folder, tmp_path, stride=8, **settings)
    with pytest.raises(DataError) as error:
        dm.setup("fit")
    message = str(error.value)
    assert f"data.dir {folder}: {found}" in message and "in the 3 training image(s)" in message
    assert f"training needs at least {needed}" in message
    min_particles = f"data.min_particles (now {settings['min_particles']})"
    for setting in ("data.stride (now 8", min_particles, "data.patch_size", "more images"):
        assert setting in message
    assert dm.patches is None
    enough = datamodule(folder, tmp_path / "ok", stride=8, min_particles=1, batch_size=5)  # 5 patches: exactly enough
    enough.setup("fit")
    assert enough.n_train == 5


def test_train_with_too_few_patches_stops_before_fit(tmp_path, monkeypatch):
    import lightning.pytorch as L
    from test_train import make_images, run_train, tiny_overrides

    monkeypatch.setattr(L.Trainer, "fit", lambda *a, **k: pytest.fail("training started on too few patches"))
    folder = make_images(tmp_path / "images", n=3, size=40, seed=2)
    with pytest.raises(DataError, match=r"only 1 24 px patch.*training needs at least 2.*data\.stride"):
        segment = [f"data.segment.{k}={v}" for k, v in (("sigma", 1.0), ("min_distance", 7), ("min_area", 40))]
        run_train(tiny_overrides(folder, tmp_path / "run", extra=["data.min_particles=2", *segment]))


# --- user settings converted with their key named -------------------------------------------------------------


def test_setting_int_and_float_name_the_key():
    from drgan.core.errors import setting_float, setting_int

    assert setting_int("k", 3) == 3 and setting_int("k", 4.0) == 4 and setting_int("k", " 5 ") == 5
    assert setting_int("k", np.int64(6), 1) == 6 and setting_float("k", "0.5") == 0.5 and setting_float("k", 2) == 2.0
    for bad in ("abc", 3.5, True, None, [1]):
        with pytest.raises(ConfigError, match=r"^k=.*: expected an integer$"):
            setting_int("k", bad)
    with pytest.raises(ConfigError, match=r"^k=0: expected an integer >= 1$"):
        setting_int("k", 0, 1)
    for bad in ("abc", float("nan"), float("inf"), None, False):
        with pytest.raises(ConfigError, match=r"^k=.*: expected a finite number$"):
            setting_float("k", bad)


def test_n_particles_not_a_number_is_named_before_mining(tmp_path):
    from hydra.errors import ConfigCompositionException
    from test_train import make_images, run_train, tiny_overrides

    folder = make_images(tmp_path / "images", n=1, size=40)
    with pytest.raises(ConfigCompositionException, match=r"material\.n_particles=abc"):  # the typed material
        run_train(tiny_overrides(folder, tmp_path / "run", extra=["material.n_particles=abc"]))
    assert not (tmp_path / "run" / "patches").exists()


def test_atomic_writes_give_the_mode_a_plain_write_would_under_any_umask(tmp_path):
    """A result written whole and renamed into place is as readable as one written directly (0666 less the umask),
    not left at the temporary file's 0600: a colleague, or a tracking server running as another user, reads it."""
    import os

    from drgan.core.io import write_bytes, write_json

    old = os.umask(0o022)
    try:
        for umask in (0o022, 0o002, 0o077):
            os.umask(umask)
            write_bytes(tmp_path / f"a{umask}.bin", b"x")
            write_json(tmp_path / f"b{umask}.json", {"k": 1})
            (tmp_path / f"plain{umask}").write_bytes(b"x")
            plain = (tmp_path / f"plain{umask}").stat().st_mode & 0o777
            assert plain == 0o666 & ~umask
            for name in (f"a{umask}.bin", f"b{umask}.json"):
                assert (tmp_path / name).stat().st_mode & 0o777 == plain, (name, oct(umask))
    finally:
        os.umask(old)
