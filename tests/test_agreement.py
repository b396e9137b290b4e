"""The weak-seed guard: a segmenter's foreground against the classical one of the user's images, and the next seed
when it covers too little (drgan.segmenters.agreement, drgan.segment's ``agreement`` block)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf
from test_segment import disc_image, disc_labels, make_generated, tiny_segment_overrides

from drgan.core.errors import ConfigError, DataError
from drgan.data.imagej import read_label_tiff, write_label_tiff
from drgan.launch.configs import compose
from drgan.segmenters.agreement import (
    Attempts,
    agreement_settings,
    foreground_agreement,
    read_reference,
    spread,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_foreground_agreement_matches_a_hand_count():
    reference = np.zeros((4, 4), bool)
    reference[0, :] = True  # 4 px
    found = np.zeros((4, 4), bool)
    found[0, :3] = True  # 3 of them
    found[1, :3] = True  # and 3 more beside
    one = foreground_agreement([reference], [found])
    assert one["covered"] == pytest.approx(3 / 4) and one["dice"] == pytest.approx(2 * 3 / (4 + 6))
    # pooled over images: a second image whose reference is fully found adds 2 px to both counts
    second = np.zeros((4, 4), bool)
    second[3, :2] = True
    two = foreground_agreement([reference, second], [found, second])
    assert two["covered"] == pytest.approx(5 / 6) and two["dice"] == pytest.approx(2 * 5 / (6 + 8))


def test_spread_takes_evenly_spaced_ids_and_all_when_few():
    ids = [f"{k:02d}" for k in range(10)]
    assert spread(ids, 20) == ids
    assert spread(list(reversed(ids)), 3) == ["00", "04", "09"]  # positions 0, 4.5 (rounded to even), 9 of the sorted
    assert len(spread(ids, 4)) == 4 and spread(ids, 4)[0] == "00" and spread(ids, 4)[-1] == "09"


@pytest.mark.parametrize(
    "node, message",
    [
        ({"reference": "r", "images": None}, "agreement.images is null"),
        ({"reference": "r", "images": "i", "min_covered": 1.5}, r"agreement.min_covered=1.5: expected a share"),
        ({"reference": "r", "images": "i", "min_dice": -0.1}, r"agreement.min_dice=-0.1: expected a share"),
        ({"reference": "r", "images": "i", "retries": -1}, r"agreement.retries=-1: expected an integer >= 0"),
        ({"reference": "r", "images": "i", "max_images": 0}, r"agreement.max_images=0: expected an integer >= 1"),
    ],
)
def test_bad_agreement_settings_are_named(node, message):
    with pytest.raises(ConfigError, match=message):
        agreement_settings(OmegaConf.create(node))


def test_no_reference_means_no_check():
    assert agreement_settings(OmegaConf.create({"reference": None, "images": "x"})) is None
    assert agreement_settings(None) is None


def _images_and_reference(folder, ids, size=40):
    import tifffile

    (folder / "images").mkdir(parents=True)
    for k, image_id in enumerate(ids):
        labels = disc_labels(size, seed=k)
        tifffile.imwrite(folder / "images" / f"{image_id}.tif", (disc_image(labels, k) * 255).astype(np.uint8))
        write_label_tiff(folder / "labels" / f"{image_id}.tif", labels)
    return folder / "images", folder / "labels"


def test_the_reference_is_read_and_checked_before_training(tmp_path):
    images, labels = _images_and_reference(tmp_path, ["a", "b", "c"])
    s = agreement_settings(OmegaConf.create({"images": str(images), "reference": str(labels), "max_images": 2}))
    items = read_reference(s)
    assert [item.id for item, _ in items] == ["a", "c"]  # spread over the sorted ids
    assert items[0][1].shape == (40, 40) and len(np.unique(items[0][1])) > 2  # the classical particles, each its id
    write_label_tiff(labels / "c.tif", np.zeros((30, 40), np.int32))
    with pytest.raises(DataError, match=r"c.tif is 40 x 30 px, the image .*c.tif 40 x 40 px"):
        read_reference(s)
    write_label_tiff(labels / "c.tif", np.zeros((40, 40), np.int32))
    write_label_tiff(labels / "zz.tif", np.zeros((40, 40), np.int32))  # an id without an image
    with pytest.raises(DataError, match=r"agreement.images=.*no image for 1 requested id\(s\): zz"):
        read_reference(agreement_settings(OmegaConf.create({"images": str(images), "reference": str(labels)})))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="no ID.tif label image in it"):
        read_reference(agreement_settings(OmegaConf.create({"images": str(images), "reference": str(empty)})))


def _attempt_files(out, tag):
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "last.ckpt").write_text(tag)
    (out / "metrics.json").write_text(json.dumps({"tag": tag, "val/dsc": 0.5}))


def test_attempts_retry_a_weak_seed_and_keep_the_best_agreeing_one(tmp_path):
    s = agreement_settings(OmegaConf.create({"images": "i", "reference": "r", "min_covered": 0.85, "retries": 2}))
    attempts = Attempts(tmp_path, s)
    assert not attempts.finished()
    _attempt_files(tmp_path, "seed0")
    attempts.stash(0, {"covered": 0.6, "dice": 0.7, "ids": ["a"]})
    assert not attempts.finished() and not (tmp_path / "checkpoints").exists()
    # a killed run resumes knowing its attempts
    assert Attempts(tmp_path, s).records == attempts.records
    _attempt_files(tmp_path, "seed1")
    attempts.stash(1, {"covered": 0.9, "dice": 0.92, "ids": ["a"]})
    assert attempts.finished()  # covered >= 0.85: no third seed
    metrics = attempts.keep_best()
    assert (tmp_path / "checkpoints" / "last.ckpt").read_text() == "seed1"
    assert metrics["tag"] == "seed1" and metrics["agreement"]["kept_seed"] == 1
    assert json.loads((tmp_path / "metrics.json").read_text())["agreement"]["attempts"][0]["covered"] == 0.6
    assert metrics["agreement"]["why"] == (
        "seed 0 covered 60% of the classical foreground (Dice 0.70), too little (at least 85%, Dice 0.60): tried "
        "seed 0 60% (Dice 0.70), seed 1 90% (Dice 0.92); kept seed 1"
    )
    assert (tmp_path / "attempts" / "0" / "checkpoints" / "last.ckpt").read_text() == "seed0"  # kept to inspect
    assert not (tmp_path / "attempts" / "1").exists()


def test_a_foreground_over_everything_is_weak_too():
    from drgan.segmenters.agreement import weak

    s = agreement_settings(OmegaConf.create({"images": "i", "reference": "r"}))
    assert weak({"covered": 1.0, "dice": 0.19}, s) and weak({"covered": 0.8, "dice": 0.9}, s)
    assert not weak({"covered": 0.9, "dice": 0.9}, s)


def test_the_retries_end_and_the_best_of_the_weak_seeds_is_kept(tmp_path):
    s = agreement_settings(OmegaConf.create({"images": "i", "reference": "r", "retries": 1}))
    attempts = Attempts(tmp_path, s)
    for seed, dice in ((0, 0.8), (1, 0.7)):
        _attempt_files(tmp_path, f"seed{seed}")
        attempts.stash(seed, {"covered": 0.5, "dice": dice, "ids": ["a"]})
    assert attempts.finished()  # one retry, both weak
    assert attempts.keep_best()["agreement"]["kept_seed"] == 0
    assert (tmp_path / "checkpoints" / "last.ckpt").read_text() == "seed0"


def guarded_run(tmp_path, *settings: str) -> tuple[list[str], Path, Path]:
    """A tiny guarded segment run's overrides (generated discs, two real images and their classical labels, no
    logger, no closed-loop check), its run folder and the reference labels' folder."""
    data = make_generated(tmp_path / "gen")
    images, labels = _images_and_reference(tmp_path / "real", ["a", "b"])
    out = tmp_path / "run"
    overrides = tiny_segment_overrides(
        data, tmp_path, out, "logger=none", "check_fraction=0", f"agreement.images={images}",
        f"agreement.reference={labels}", "agreement.crop_rows=null", *settings,
    )  # fmt: skip
    return overrides, out, labels


def test_segment_with_the_check_trains_another_seed_when_the_first_covers_too_little(tmp_path):
    from drgan.segment import segment

    overrides, out, _ = guarded_run(
        tmp_path, "trainer.max_epochs=1", "split_calibration=null", "agreement.min_covered=1.0", "agreement.retries=1"
    )
    metrics = segment(compose(overrides, config_name="segment"))
    written = json.loads((out / "metrics.json").read_text())
    agreement = written["agreement"]
    # a tiny segmenter never covers all of the classical foreground: both seeds tried, the better-agreeing kept
    assert [a["seed"] for a in agreement["attempts"]] == [0, 1]
    best = max(agreement["attempts"], key=lambda a: a["dice"])
    assert agreement["kept_seed"] == best["seed"] and (out / "checkpoints" / "last.ckpt").is_file()
    assert all(0.0 <= a["covered"] <= 1.0 and a["ids"] == ["a", "b"] for a in agreement["attempts"])
    other = 1 - best["seed"]
    assert (out / "attempts" / str(other) / "checkpoints" / "last.ckpt").is_file()
    assert metrics["val/dsc"] == written["val/dsc"]
    # done: running it again changes nothing and trains nothing
    again = segment(compose([*overrides, "ckpt_path=last"], config_name="segment"))
    assert again == metrics and json.loads((out / "metrics.json").read_text()) == written


def test_each_attempt_has_an_early_stopping_of_its_own(tmp_path):
    from drgan.segment import segment

    overrides, out, _ = guarded_run(
        tmp_path, "trainer.max_epochs=3", "split_calibration=null", "agreement.min_covered=1.0", "agreement.retries=1",
        "early_stopping.patience=1", "early_stopping.min_delta=1000",  # no epoch improves on the first one
    )  # fmt: skip
    segment(compose(overrides, config_name="segment"))
    attempts = [json.loads(m.read_text()) for m in sorted((out / "attempts").glob("*/metrics.json"))]
    attempts.append(json.loads((out / "metrics.json").read_text()))  # the kept one is back in the run folder
    # each attempt: epoch 0 sets its best, epoch 1 does not beat it by 1000: stopped after 2 epochs (a stopper shared
    # with the first attempt stopped the second after its epoch 0)
    assert len(attempts) == 2 and all(m["epoch"] == 2 and "patience" in m["stop_reason"] for m in attempts), attempts


def test_segment_checks_its_calibrated_split_on_the_users_images_against_the_classical_count(tmp_path):
    from drgan.segment import segment

    overrides, out, labels = guarded_run(
        tmp_path, "trainer.max_epochs=1", "agreement.min_covered=0.0", "agreement.min_dice=0.0"
    )
    segment(compose(overrides, config_name="segment"))
    calibration = json.loads((out / "metrics.json").read_text())["split_calibration"]
    guard = calibration["real_count"]
    classical = sum(int((np.bincount(read_label_tiff(labels / f"{k}.tif")[0].ravel())[1:] >= 8).sum()) for k in "ab")
    assert guard["images"] == 2 and guard["classical"] == classical > 0
    # what was stored is what the guard decided: the choice moved only when it counted more than 10 % fewer
    chosen = {k: calibration[k] for k in guard["from"]}
    assert (chosen != guard["from"]) == guard["moved"]
    assert guard["moved"] == (guard["chosen_count"] < 0.9 * classical and guard["count"] != guard["chosen_count"])


def test_segment_refuses_a_bad_reference_before_training(tmp_path):
    from drgan.segment import segment

    data = make_generated(tmp_path / "gen")
    out = tmp_path / "run"
    overrides = tiny_segment_overrides(
        data, tmp_path, out, "logger=none", f"agreement.images={tmp_path}", f"agreement.reference={tmp_path / 'no'}"
    )
    with pytest.raises(DataError, match=r"agreement.reference=.*no: no such folder"):
        segment(compose(overrides, config_name="segment"))
    assert not (out / "checkpoints").exists()


def test_the_reports_segment_line_says_which_seed_was_kept(tmp_path):
    from drgan.pipeline.report import segment_summary

    s = agreement_settings(OmegaConf.create({"images": "i", "reference": "r"}))
    attempts = Attempts(tmp_path, s)
    for seed, covered in ((0, 0.5), (1, 0.9)):
        _attempt_files(tmp_path, f"seed{seed}")
        attempts.stash(seed, {"covered": covered, "dice": covered, "ids": ["a"]})
    attempts.keep_best()
    summary = segment_summary(tmp_path)
    assert summary["line"].endswith("tried seed 0 50% (Dice 0.50), seed 1 90% (Dice 0.90); kept seed 1")
    assert summary["metrics"]["segment/classical_covered"] == 0.9 and summary["metrics"]["segment/attempts"] == 2
