"""drgan.metrics.two_sample and `python -m drgan.realism`: the classifier two-sample test on tiny patches (16-32 px).

The statistics are checked against scipy and hand-computed cases; the test itself on samples whose answer is
known (two clearly different noise levels -> accuracy near 1; one distribution split in two -> 0.5 inside the
interval); the command line on tiny disc images with a split (real vs real, a generated dataset, a checkpoint).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import compose
from PIL import Image

from drgan.core.errors import ConfigError, DataError
from drgan.metrics import two_sample as ts

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = ts.ClassifierSettings(folds=4, epochs=5, input_size=24, batch_size=16, width=8)


def noise_patches(n, sigma, rng, size=24):
    return np.clip(0.5 + sigma * rng.standard_normal((n, size, size)), 0, 1).astype(np.float32)


# --- statistics ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("k,n", [(0, 10), (3, 10), (5, 10), (10, 10), (57, 126), (230, 252), (1, 1)])
def test_intervals_match_scipy_binomtest(k, n):
    from scipy.stats import binomtest

    result = binomtest(k, n)
    for mine, method in ((ts.exact_interval(k, n), "exact"), (ts.wilson_interval(k, n), "wilson")):
        theirs = result.proportion_ci(0.95, method=method)
        assert mine == pytest.approx((theirs.low, theirs.high), abs=1e-9), method
    assert ts.p_above_chance(k, n) == pytest.approx(binomtest(k, n, 0.5, alternative="greater").pvalue, rel=1e-9)


def test_intervals_and_p_value_by_hand():
    # Clopper-Pearson at the ends: k = 0 -> [0, 1 - (alpha/2)^(1/n)]; k = n -> [(alpha/2)^(1/n), 1].
    assert ts.exact_interval(0, 10) == pytest.approx((0.0, 1 - 0.025**0.1))
    assert ts.exact_interval(10, 10) == pytest.approx((0.025**0.1, 1.0))
    assert ts.exact_interval(5, 10) == pytest.approx((0.187086, 0.812914), abs=1e-6)  # textbook value
    # Wilson at p = 0.5, n = 10: centre 0.5, half width z sqrt(0.025 + z^2/400) / (1 + z^2/10), z = 1.959964.
    z = 1.959964
    half = z * math.sqrt(0.025 + z * z / 400) / (1 + z * z / 10)
    assert ts.wilson_interval(5, 10) == pytest.approx((0.5 - half, 0.5 + half), abs=1e-6)
    assert ts.p_above_chance(10, 10) == pytest.approx(0.5**10)
    assert ts.p_above_chance(0, 10) == pytest.approx(1.0)
    assert ts.p_above_chance(6, 10) == pytest.approx((210 + 120 + 45 + 10 + 1) / 1024)


def test_auc_by_hand_and_against_sklearn():
    from sklearn.metrics import roc_auc_score

    assert ts.auc([0.1, 0.2, 0.8, 0.9], [0, 0, 1, 1]) == 1.0
    assert ts.auc([0.9, 0.8, 0.2, 0.1], [0, 0, 1, 1]) == 0.0
    # A tie counts half. Label 1 scores {0.5, 0.7}, label 0 {0.5, 0.2}: 0.7 beats both (2 pairs), 0.5 beats 0.2
    # (1) and ties 0.5 (0.5): 3.5 of 4 pairs.
    assert ts.auc([0.5, 0.2, 0.5, 0.7], [0, 0, 1, 1]) == pytest.approx(3.5 / 4)
    rng = np.random.default_rng(1)
    scores, labels = rng.integers(0, 5, 60).astype(float), rng.integers(0, 2, 60)
    assert ts.auc(scores, labels) == pytest.approx(roc_auc_score(labels, scores))


def test_group_folds_keep_a_group_together_and_spread_each_label():
    labels = np.r_[np.zeros(30), np.ones(30)]
    groups = [f"img{i // 3}" for i in range(30)] + [f"syn{i}" for i in range(30)]
    fold = ts.group_folds(labels, groups, 5, seed=0)
    for g in set(groups):
        assert len({fold[i] for i in range(60) if groups[i] == g}) == 1
    for label in (0, 1):
        assert np.bincount(fold[labels == label], minlength=5).tolist() == [6] * 5
    with pytest.raises(ConfigError, match="both labels"):
        ts.group_folds(np.array([0, 1]), ["x", "x"], 2, seed=0)


# --- the test on known answers ----------------------------------------------------------------------------


def test_two_clearly_different_samples_are_told_apart():
    rng = np.random.default_rng(0)
    result = ts.two_sample_test(noise_patches(40, 0.05, rng), noise_patches(40, 0.2, rng), TINY, progress=False)
    assert result["total"] == 80 and result["n_per_class"] == 40
    assert result["accuracy"] >= 0.9 and result["interval"][0] > 0.5 and result["auc"] > 0.95
    assert result["p_value"] < 1e-6
    assert sum(f["test_patches"] for f in result["folds"]) == 80


def test_one_distribution_split_in_two_is_not_told_apart():
    rng = np.random.default_rng(0)
    same = noise_patches(80, 0.1, rng)
    result = ts.two_sample_test(same[:40], same[40:], TINY, progress=False)
    low, high = result["interval"]
    assert low <= 0.5 <= high and result["p_value"] > 0.05
    # Deterministic: fixed seeds give the same predictions.
    again = ts.two_sample_test(same[:40], same[40:], TINY, progress=False)
    assert again["correct"] == result["correct"] and again["auc"] == result["auc"]


def test_unbalanced_samples_are_balanced_to_the_smaller():
    rng = np.random.default_rng(0)
    result = ts.two_sample_test(
        noise_patches(12, 0.05, rng),
        noise_patches(30, 0.2, rng),
        ts.ClassifierSettings(folds=3, epochs=2, input_size=12, width=4),
        progress=False,
    )
    assert result["n_per_class"] == 12 and result["total"] == 24 and result["available"] == {"A": 12, "B": 30}


@pytest.mark.parametrize(
    "a_shape,b_shape,settings,error,message",
    [
        ((20, 24, 24), (20, 32, 32), TINY, DataError, "one size"),
        ((5, 24, 24), (20, 24, 24), TINY, DataError, "at least 8"),
        ((20, 24, 20), (20, 24, 20), TINY, DataError, "square"),
        ((20, 16, 16), (20, 16, 16), TINY, ConfigError, "input_size=24"),
        ((20, 24, 24), (20, 24, 24), ts.ClassifierSettings(folds=1), ConfigError, "test.folds"),
        ((20, 24, 24), (20, 24, 24), ts.ClassifierSettings(lr=0.0), ConfigError, "test.lr"),
    ],
)
def test_bad_inputs_raise_before_training(a_shape, b_shape, settings, error, message):
    with pytest.raises(error, match=message):
        ts.two_sample_test(np.zeros(a_shape, np.float32), np.zeros(b_shape, np.float32), settings, progress=False)


def test_bad_samples_and_counts_raise():
    good = np.zeros((20, 24, 24), np.float32)
    with pytest.raises(DataError, match="finite"):
        ts.two_sample_test(np.full_like(good, np.nan), good, TINY, progress=False)
    with pytest.raises(DataError, match="cannot fill 4 folds"):  # A: 20 patches of 2 images -> only 2 folds
        ts.two_sample_test(good, good, TINY, groups_a=["x"] * 10 + ["y"] * 10, progress=False)
    with pytest.raises(ConfigError, match="group names"):
        ts.two_sample_test(good, good, TINY, groups_a=["x"], progress=False)
    for k, n in ((11, 10), (-1, 10), (0, 0)):
        with pytest.raises(ConfigError, match="binomial counts"):
            ts.exact_interval(k, n)
    with pytest.raises(ConfigError, match="confidence"):
        ts.wilson_interval(1, 2, confidence=1.5)


# --- the command line ------------------------------------------------------------------------------------


SIZE = 24
TEST_ID = "img9"


def disc_images(folder: Path, n_train: int = 6, seed: int = 0) -> Path:
    """Bright discs on a dark background (tests/test_train.py's images), with a split.json holding out one
    (flat grey) test image, img9, that no result may name."""
    from test_train import make_images

    make_images(folder, n=n_train, seed=seed)
    Image.fromarray(np.full((96, 96), 200, np.uint8)).save(folder / f"{TEST_ID}.png")
    split = {"train": [f"img{i}" for i in range(n_train)], "test": [TEST_ID]}
    (folder / "split.json").write_text(json.dumps(split))
    return folder


def realism_cfg(images: Path, out: Path, synthetic, *extra):
    return compose(
        [
            f"data.dir={images}",
            f"synthetic={synthetic}",
            f"out={out}",
            f"data.patch_size={SIZE}",
            "data.crop_rows=null",
            "data.stride=12",
            "data.min_particles=1",
            "data.n_background=2",
            "test.folds=2",
            "test.epochs=2",
            f"test.input_size={SIZE // 2}",
            "test.width=4",
            "progress=false",
            "fid=false",
            *extra,
        ],
        config_name="realism",
    )


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    return disc_images(tmp_path_factory.mktemp("real") / "images")


def test_cli_real_vs_real_halves_by_image_and_never_reads_test_ids(images, tmp_path, monkeypatch):
    from drgan.callbacks.fid import RandomProjectionFeatures
    from drgan.metrics import inception
    from drgan.realism import RealismSettings, realism

    monkeypatch.setattr(inception, "InceptionFeatures", lambda: RandomProjectionFeatures(dim=8))  # FID beside the test
    summary = realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "out", "real", "fid=true")))
    assert np.isfinite(summary["test"]["fid"]) and summary["test"]["fid"] >= 0 and "kid" in summary["test"]
    assert summary["markdown"].endswith(f" {summary['test']['fid']:.1f} |")
    source, test = summary["source"], summary["test"]
    assert set(source["half_a_ids"]).isdisjoint(source["half_b_ids"])
    assert set(source["half_a_ids"]) | set(source["half_b_ids"]) == {f"img{i}" for i in range(6)}
    assert TEST_ID not in summary["real"]["train_ids"] and TEST_ID not in json.dumps(source)
    assert test["n_per_class"] >= 4 and 2 <= test["groups"] <= 6
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert saved["test"]["accuracy"] == test["accuracy"]
    lines = (tmp_path / "out" / "results.md").read_text().splitlines()
    assert lines[0].startswith("| source |") and lines[2] == summary["markdown"] and "real vs real" in lines[2]


def write_dataset(folder: Path, images: np.ndarray, n_background: int = 2) -> Path:
    """A generated-dataset folder as drgan.synthetic reads it: manifest.json listing synthetic and background items."""
    from drgan.core.io import write_json, write_png
    from drgan.synthetic import BACKGROUND, SYNTHETIC, bg_id, item_files, syn_id

    entries = []
    for i in range(len(images)):
        entries.append({"id": syn_id(i), "kind": SYNTHETIC, "index": i, "files": item_files(syn_id(i))})
    for j in range(n_background):  # real backgrounds that generate adds: the test must leave them out
        entries.append({"id": bg_id(j), "kind": BACKGROUND, "files": item_files(bg_id(j))})
    for entry, image in zip(entries, list(images) + [np.ones((SIZE, SIZE))] * n_background):
        write_png(folder / entry["files"]["image"], image)
        write_png(folder / entry["files"]["mask"], np.zeros(image.shape, np.uint8))
    write_json(folder / "manifest.json", {"entries": entries})
    return folder


def test_cli_reads_a_generated_dataset_and_tells_flat_grey_images_from_discs(images, tmp_path):
    from drgan.realism import RealismSettings, realism

    rng = np.random.default_rng(0)
    flat = np.clip(0.5 + 0.01 * rng.standard_normal((40, SIZE, SIZE)), 0, 1)
    data = write_dataset(tmp_path / "dataset", flat)
    summary = realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "out", data, "test.epochs=6")))
    assert summary["source"]["kind"] == "dataset"
    assert summary["test"]["accuracy"] >= 0.9 and summary["test"]["interval"][0] > 0.5

    wrong = write_dataset(tmp_path / "wrong", np.zeros((10, 32, 32)))
    with pytest.raises(DataError, match="32 x 32 px, but the real patches are 24 x 24"):
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "out2", wrong)))


def test_cli_renders_a_checkpoint(images, tmp_path):
    from test_train import run_train, tiny_overrides

    from drgan.realism import RealismSettings, realism

    run = tmp_path / "run"
    run_train(tiny_overrides(images, run, extra=["trainer.max_epochs=1", "trainer.limit_train_batches=1"]))
    summary = realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "out", run, "n_synthetic=12")))
    assert summary["source"]["kind"] == "checkpoint" and summary["source"]["resolution"] == SIZE
    assert summary["source"]["quantized_8bit"] and summary["source"]["synthetic_read"] == 12
    assert summary["test"]["n_per_class"] == 12 and summary["source"]["parameters"] == "trained"
    middle = realism(
        RealismSettings.from_config(
            realism_cfg(images, tmp_path / "mid", run, "n_synthetic=12", "render.parameters=middle")
        )
    )
    assert middle["source"]["parameters"] == "middle" and middle["source"]["label"].endswith("(middle values)")
    with pytest.raises(DataError, match="renders 24 px images"):
        realism(
            RealismSettings.from_config(
                realism_cfg(
                    images,
                    tmp_path / "out2",
                    run / "checkpoints" / "best.ckpt",
                    "data.patch_size=16",
                    "test.input_size=8",
                )
            )
        )


def test_cli_bad_inputs(images, tmp_path):
    from drgan.realism import RealismSettings, realism

    with pytest.raises(ConfigError, match="synthetic=real"):
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "o", "null")))
    with pytest.raises(ConfigError, match="no such file or folder"):
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "o", tmp_path / "missing")))
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ConfigError, match="not a .ckpt"):
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "o", tmp_path / "notes.txt")))
    with pytest.raises(ConfigError, match="data.dir"):
        realism(
            RealismSettings.from_config(compose(["synthetic=real", f"out={tmp_path / 'o'}"], config_name="realism"))
        )
    with pytest.raises(DataError, match="at least 40"):  # too few real patches for 20 folds
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "o", "real", "test.folds=20")))
    with pytest.raises(ConfigError, match=r"test: unknown setting.*colour"):
        realism(RealismSettings.from_config(realism_cfg(images, tmp_path / "o", "real", "+test.colour=1")))
