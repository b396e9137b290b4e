"""The instance-aware segmenter (drgan.segmenters.instances): its centre-map targets from hand-made instance maps,
exactly against a brute-force distance; its split on hand-made probabilities; a few training steps through
drgan.segment, drgan.evaluate and drgan.analyze; instance maps as annotations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import compose
from PIL import Image
from test_segment import disc_image, disc_labels, eval_cfg, make_real, tiny_segment_overrides

from drgan.core.errors import ConfigError
from drgan.scene.labels import centre_distance, class_mask

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def brute_centre_distance(labels: np.ndarray) -> np.ndarray:
    """The target by definition: per particle pixel, the distance to the nearest pixel of another id, where the
    image is extended past its border by repeating its edge (a cut particle goes on); over the particle's maximum."""
    h, w = labels.shape
    pad = max(h, w)
    extended = np.pad(labels, pad, mode="edge")
    ys, xs = np.mgrid[: extended.shape[0], : extended.shape[1]]
    out = np.zeros(labels.shape)
    for k in np.unique(labels[labels > 0]):
        other_y, other_x = ys[extended != k], xs[extended != k]
        py, px = np.nonzero(labels == k)
        d = np.sqrt((py[:, None] + pad - other_y[None]) ** 2 + (px[:, None] + pad - other_x[None]) ** 2).min(axis=1)
        out[py, px] = d / d.max()
    return out


def touching_pair() -> np.ndarray:
    labels = np.zeros((14, 22), np.int32)
    yy, xx = np.mgrid[:14, :22]
    labels[(yy - 7) ** 2 + (xx - 6) ** 2 <= 25] = 1
    labels[((yy - 7) ** 2 + (xx - 14) ** 2 <= 25) & (labels == 0)] = 2  # they touch along column 10-11
    return labels


def ring() -> np.ndarray:
    yy, xx = np.mgrid[:21, :21]
    r2 = (yy - 10) ** 2 + (xx - 10) ** 2
    return ((r2 <= 64) & (r2 > 16)).astype(np.int32)


def cut_by_the_border() -> np.ndarray:
    labels = np.zeros((12, 16), np.int32)
    yy, xx = np.mgrid[:12, :16]
    labels[(yy - 0) ** 2 + (xx - 8) ** 2 <= 36] = 1  # a disc whose centre lies on the top row: its lower half
    return labels


@pytest.mark.parametrize("make", [touching_pair, ring, cut_by_the_border])
def test_centre_targets_equal_their_definition_on_hand_made_instance_maps(make):
    labels = make()
    np.testing.assert_allclose(centre_distance(labels), brute_centre_distance(labels), atol=1e-6)


def test_centre_targets_fall_to_the_contact_line_and_peak_on_each_core():
    labels = touching_pair()
    target = centre_distance(labels)
    assert target[labels == 1].max() == 1.0 and target[labels == 2].max() == 1.0 and target[6, 6] > 0.8  # cores
    row = target[7]
    contact = int(np.argmin(row[7:15])) + 7
    assert row[contact] <= 0.25 and 9 <= contact <= 11  # the valley where they touch
    assert row[6] > 3 * row[contact] and row[14] > 3 * row[contact]
    ring_target = centre_distance(ring())
    across = ring_target[10, 2:6]  # radius 8 (outer edge) to 5 (inner edge)
    assert ring_target[10, 10] == 0 and across.argmax() in (1, 2) and across.max() >= 2 * max(across[0], across[-1])
    cut = centre_distance(cut_by_the_border())
    assert cut[0, 8] == 1.0  # the border is no boundary: the core lies on it


def _probs(labels: np.ndarray, centre: np.ndarray) -> np.ndarray:
    particle = labels > 0
    probs = np.zeros((4, *labels.shape), np.float32)
    probs[0], probs[1], probs[3] = np.where(particle, 0.05, 0.9), np.where(particle, 0.9, 0.05), centre
    probs[2] = 1 - probs[0] - probs[1]
    return probs


def test_split_by_centres_separates_touching_particles_the_class_map_merges():
    from drgan.metrics.instance_scores import binarize_and_label, match_instances
    from drgan.segmenters.inference import split_by_centres

    truth = touching_pair()
    probs = _probs(truth, centre_distance(truth))  # the classes merge them; the centre map has two cores
    assert binarize_and_label(probs[:3].argmax(0).astype(np.int64)).max() == 1
    found = binarize_and_label(split_by_centres(probs, 0.5).astype(np.int64))
    match = match_instances(found, truth, 0.5)
    assert (match.tp, match.fp, match.fn) == (2, 0, 0) and match.ious.min() > 0.8
    flat = _probs(truth, np.where(truth > 0, 0.9, 0.0))  # no valley: one seed, one particle
    assert binarize_and_label(split_by_centres(flat, 0.5).astype(np.int64)).max() == 1
    with pytest.raises(ConfigError, match="seed_level"):
        split_by_centres(probs, 1.5)


def make_generated_with_labels(folder: Path, n: int = 6, size: int = 32) -> Path:
    for d in ("images", "masks", "labels"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        labels = disc_labels(size, n=4, seed=i)
        Image.fromarray((disc_image(labels, i) * 255).astype(np.uint8)).save(folder / "images" / f"{i:03d}.png")
        Image.fromarray(class_mask(labels, 1)).save(folder / "masks" / f"{i:03d}.png")
        Image.fromarray(labels.astype(np.uint8)).save(folder / "labels" / f"{i:03d}.png")
    return folder


def test_the_crops_carry_the_centre_targets_of_the_whole_image_cut_and_turned_with_the_mask(tmp_path):
    from drgan.segmenters.pairs import CropDataset, load_generated_pairs

    pairs = load_generated_pairs(make_generated_with_labels(tmp_path / "g"))
    assert pairs[0].labels is not None and pairs[0].labels.max() >= 1
    crops = CropDataset(pairs, crop=24, augment=True, centres=True, seed=0)
    image, mask, centre = crops[0]
    assert image.shape == (1, 24, 24) and mask.shape == centre.shape == (24, 24)
    # the target is 0 exactly off the particles and positive on them, whatever flip and rotation the crop got
    assert torch.all((centre > 0) == (mask > 0))
    plain = CropDataset(pairs, crop=24, augment=False)
    assert len(plain[0]) == 2  # a U-Net's crops as before


def test_a_few_training_steps_through_segment_evaluate_and_analyze(tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.segment import segment
    from drgan.segmenters.registry import load_segmenter

    data = make_generated_with_labels(tmp_path / "gen")
    out = tmp_path / "run"
    overrides = tiny_segment_overrides(
        data, tmp_path, out, "logger=none", "trainer.max_epochs=2",
        "model._target_=drgan.segmenters.instances.CentreSegmenterModule", "+model.distance_weight=5.0",
    )  # fmt: skip
    metrics = segment(compose(overrides, config_name="segment"))
    assert "train/centre_mse" in metrics and np.isfinite(metrics["val/loss"])
    calibration = json.loads((out / "metrics.json").read_text())["split_calibration"]
    assert calibration["split"] == "centres" and calibration["seed_level"] in (0.3, 0.4, 0.5, 0.6, 0.7)
    assert len(calibration["table"]) == 5
    model = load_segmenter(out / "checkpoints" / "last.ckpt")
    assert model.instance_split == "centres" and model.split_calibration["seed_level"] == calibration["seed_level"]

    labels = disc_labels(40, n=4, seed=7)
    real = make_real(tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255},
                     {"train": [], "test": ["x"]})  # fmt: skip
    last = out / "checkpoints" / "last.ckpt"
    result = evaluate(
        EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval", [f"model={last}", "inference.tile=32"]))
    )
    assert 0.0 <= result["mean"]["dsc"] <= 1.0
    assert f"seed_level {calibration['seed_level']}" in (tmp_path / "eval" / "results.md").read_text()
    rows = analyze(AnalyzeSettings.from_config(compose([f"images={real / 'images'}", f"out={tmp_path / 'an'}", f"model={last}",
                            "inference.tile=32"], config_name="analyze")))  # fmt: skip
    assert (tmp_path / "an" / "particles.csv").is_file() and isinstance(rows, list)


def test_an_instance_map_annotation_keeps_touching_particles_apart(tmp_path):
    import tifffile

    from drgan.segmenters.pairs import load_real_items

    labels = touching_pair().astype(np.uint16) * 300  # ids 300 and 600: a 16-bit instance map
    folder = tmp_path / "real"
    for d in ("images", "masks"):
        (folder / d).mkdir(parents=True)
    tifffile.imwrite(folder / "images" / "a.tif", (disc_image(labels > 0) * 255).astype(np.uint8))
    tifffile.imwrite(folder / "masks" / "a.tif", labels)
    (item, found), = load_real_items(folder, ["a"])  # fmt: skip
    assert found.max() == 2 and ((found > 0) == (labels > 0)).all()
    # the same particles as a binary mask: touching, so one 4-connected component
    tifffile.imwrite(folder / "masks" / "a.tif", ((labels > 0) * 255).astype(np.uint8))
    assert load_real_items(folder, ["a"])[0][1].max() == 1


def test_a_pair_shrunk_to_the_working_scale_keeps_its_instances_exactly():
    from drgan.scene.labels import IGNORE
    from drgan.segmenters.pairs import Pair, rescale_pair

    small = touching_pair()
    big = np.kron(small, np.ones((4, 4), np.int32))  # every pixel a 4 x 4 block
    mask = class_mask(big, 1)
    mask[:8, :8] = IGNORE  # two blocks no class is known for
    image = (big > 0).astype(np.float32) * 0.8 + 0.1
    shrunk = rescale_pair(Pair("p", image, mask, big), 0.25, contour_px=1)
    assert shrunk.image.shape == small.shape and shrunk.image.dtype == np.float32
    assert (shrunk.labels == small).all()  # nearest neighbour from each new pixel's centre: the blocks' ids
    expected = class_mask(small, 1)
    expected[:2, :2] = IGNORE
    assert (shrunk.mask == expected).all()
    # area-averaged: flat inside a particle and outside, the particles' share of grey on the outline
    assert shrunk.image[7, 6] == pytest.approx(0.9, abs=1e-3) and shrunk.image[0, 21] == pytest.approx(0.1, abs=1e-3)


def test_the_working_scale_follows_the_median_particle_and_stops_at_one_crop():
    from drgan.metrics.statistics import particles
    from drgan.segmenters.pairs import MAX_ENLARGE, Pair, working_scale

    labels = [disc_labels(128, n=4, seed=s) for s in range(3)]
    pairs = [Pair(str(k), disc_image(lab), class_mask(lab, 1), lab) for k, lab in enumerate(labels)]
    median = float(np.median(np.concatenate([particles(lab).diameter for lab in labels])))
    scale, measured = working_scale(pairs, median / 4, crop=16)
    assert measured == pytest.approx(median) and scale == pytest.approx(0.25)
    assert working_scale(pairs, median / 4, crop=64)[0] == pytest.approx(0.5)  # 128-px pairs keep a 64-px crop
    assert working_scale(pairs, 2 * median, crop=16)[0] == 1.0  # particles already smaller: unchanged
    assert working_scale(pairs, None, crop=16)[0] == 1.0  # off
    # loader.min_working_px: smaller particles enlarged to it, at most MAX_ENLARGE times; larger ones left alone
    assert working_scale(pairs, None, crop=16, min_px=2 * median)[0] == pytest.approx(2.0)
    assert working_scale(pairs, None, crop=16, min_px=100 * median)[0] == MAX_ENLARGE
    assert working_scale(pairs, None, crop=16, min_px=median / 2)[0] == 1.0


def test_the_working_scale_is_measured_on_pairs_that_hold_particles():
    """A generated set lists its background pairs first: they must not hide the particles' size."""
    from drgan.segmenters.pairs import WORKING_SAMPLE, Pair, sample_diameters, working_scale

    empty = np.zeros((64, 64), np.int32)
    backgrounds = [Pair(f"pbg_{k}", disc_image(empty), class_mask(empty, 1), empty) for k in range(WORKING_SAMPLE)]
    lab = disc_labels(64, n=4, seed=0)
    pairs = [*backgrounds, Pair("syn_0", disc_image(lab), class_mask(lab, 1), lab)]
    assert sample_diameters(pairs).size == 4
    assert working_scale(pairs, None, crop=16, min_px=4 * float(np.median(sample_diameters(pairs))))[0] == 4.0


def test_a_pair_enlarged_to_the_working_scale_keeps_its_instances_and_redraws_its_contour():
    from drgan.segmenters.pairs import Pair, rescale_pair

    small = touching_pair()
    image = (small > 0).astype(np.float32) * 0.8 + 0.1
    big = rescale_pair(Pair("p", image, class_mask(small, 1), small), 3.0, contour_px=3)
    assert big.image.shape == (3 * small.shape[0], 3 * small.shape[1])
    assert (big.labels == np.kron(small, np.ones((3, 3), np.int32))).all()  # each old pixel a 3 x 3 block
    assert (big.mask == class_mask(big.labels, 3)).all()  # the contour 3 px wide: the same width in real px
    # bilinear: inside a particle and far outside the grey stays, between them it passes through the middle
    assert big.image.min() >= 0.1 - 1e-6 and big.image.max() <= 0.9 + 1e-6


def test_the_instance_aware_segmenter_learns_at_its_working_scale_and_infers_at_the_same(tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate
    from drgan.metrics.statistics import area_median, diameters_of
    from drgan.segment import LoaderSettings, segment, working_px_of
    from drgan.segmenters.module import SegmenterModule
    from drgan.segmenters.pairs import CENTRE_WORKING_PX
    from drgan.segmenters.registry import load_segmenter

    assert working_px_of("auto", SegmenterModule) is None  # the U-Net: pairs as they are
    assert working_px_of("auto", type("Centres", (), {"needs_centres": True})) == CENTRE_WORKING_PX
    for bad in (0.5, "large"):
        with pytest.raises(ConfigError, match="loader.working_px"):
            LoaderSettings.from_config(compose([f"loader.working_px={bad}"], config_name="segment"))

    data = make_generated_with_labels(tmp_path / "gen", n=4, size=64)
    out = tmp_path / "run"
    overrides = tiny_segment_overrides(
        data, tmp_path, out, "logger=none", "trainer.max_epochs=1", "loader.working_px=4",
        "model._target_=drgan.segmenters.instances.CentreSegmenterModule",
    )  # fmt: skip
    segment(compose(overrides, config_name="segment"))
    model = load_segmenter(out / "checkpoints" / "last.ckpt")
    assert model.pixel_scale == pytest.approx(0.5)  # 64-px pairs shrunk to one 32-px crop, not to 4-px particles
    assert json.loads((out / "metrics.json").read_text())["pixel_scale"] == pytest.approx(0.5)
    # the pairs' area-weighted median particle after shrinking: what inference's pixel_scale=per_image brings each image's to
    median = area_median(diameters_of([disc_labels(64, n=4, seed=i) for i in range(4)]))
    assert model.working_diameter == pytest.approx(0.5 * median, abs=1e-3)
    assert json.loads((out / "metrics.json").read_text())["working_diameter"] == model.working_diameter
    labels = disc_labels(48, n=4, seed=7)
    real = make_real(tmp_path / "real", {"x": disc_image(labels)}, {"x": (labels > 0) * 255},
                     {"train": [], "test": ["x"]})  # fmt: skip
    result = evaluate(EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval", [f"model={out / 'checkpoints' / 'last.ckpt'}",
                                                          "inference.tile=32"])))  # fmt: skip
    assert 0.0 <= result["mean"]["dsc"] <= 1.0  # the 48-px image shrunk to 24 px, its class map brought back
    per_image = evaluate(EvaluateSettings.from_config(eval_cfg(real, tmp_path / "eval_per_image", [f"model={out / 'checkpoints' / 'last.ckpt'}",
                                                                      "inference.tile=32",
                                                                      "inference.pixel_scale=per_image"])))  # fmt: skip
    assert 0.0 <= per_image["mean"]["dsc"] <= 1.0
