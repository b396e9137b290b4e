"""The touching-particle split chosen per segmenter on its validation pairs (drgan.segmenters.calibrate)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from drgan.core.errors import ConfigError
from drgan.scene.labels import class_mask
from drgan.segmenters.pairs import Pair


class ProbabilityImage(torch.nn.Module):
    """A stand-in network whose input *is* its particle probability p: classes (background, particle, contour) =
    ((1 - p) 0.8, p, (1 - p) 0.2), so a test sets the probabilities the split sees exactly."""

    def forward(self, x):
        p = x.clamp(1e-4, 1 - 1e-4)
        return torch.log(torch.cat([(1 - p) * 0.8, p, (1 - p) * 0.2], dim=1))


def _two_touching_discs(size=48, r=10.0, gap=7.0):
    """Labels of two discs whose centres are ``gap`` px apart, their overlap split at the midline (each pixel to
    the nearer centre), so that the true contact line is where a symmetric split cuts."""
    yy, xx = np.mgrid[:size, :size]
    c = size / 2
    centres = (c - gap / 2 - 0.5, c + gap / 2 - 0.5)
    inside = [(yy - c + 0.5) ** 2 + (xx - cx) ** 2 <= r * r for cx in centres]
    nearer_first = np.abs(xx - centres[0]) < np.abs(xx - centres[1])
    labels = np.zeros((size, size), np.int32)
    labels[(inside[0] | inside[1]) & nearer_first] = 1
    labels[(inside[0] | inside[1]) & ~nearer_first] = 2
    return labels


def _pair(labels: np.ndarray, neck_probability: float | None = None) -> Pair:
    """Two discs (labels) as a validation pair: the image is the particle probability (0.97 inside), lowered to
    ``neck_probability`` on the 4 columns around their contact line."""
    image = np.where(labels > 0, 0.97, 0.0).astype(np.float32)
    if neck_probability is not None:
        neck = (labels > 0) & (np.abs(np.arange(labels.shape[1]) - labels.shape[1] / 2 + 0.5) <= 1.5)[None, :]
        image[neck] = neck_probability
    return Pair("p", image, class_mask(labels, 1))


def test_the_core_that_opens_an_unsure_neck_is_chosen_and_the_table_is_exact():
    from drgan.segmenters.calibrate import calibrate_split

    pair = _pair(_two_touching_discs(r=10.0, gap=7.0), neck_probability=0.6)
    result = calibrate_split(
        ProbabilityImage(), [pair, pair], {"cores": [None, 0.7], "depths": [2.0], "seeds": ["hmaxima"]}, tile=48
    )
    argmax, strict = result["table"]
    # the argmax core sees one blob per image, matching neither disc (IoU < 0.5 with each half)
    assert (argmax["tp"], argmax["fp"], argmax["fn"]) == (0, 2, 4) and argmax["ap50"] == 0.0
    assert (strict["tp"], strict["fp"], strict["fn"]) == (4, 0, 0) and strict["ap50"] == 1.0
    assert (result["split_core"], result["split_depth"], result["ap50"], result["n_pairs"]) == (0.7, 2.0, 1.0, 2)


def test_ties_keep_the_more_lenient_setting_and_max_pairs_caps_the_work():
    from drgan.segmenters.calibrate import calibrate_split

    apart = _pair(_two_touching_discs(r=7.0, gap=20.0))  # well apart: every setting finds both
    result = calibrate_split(
        ProbabilityImage(),
        [apart] * 5,
        {"cores": [None, 0.9], "depths": [1.0, 2.0], "max_pairs": 3, "seeds": ["hmaxima"]},
        tile=48,
    )
    assert all(row["ap50"] == 1.0 for row in result["table"]) and len(result["table"]) == 4
    assert (result["split_depth"], result["split_core"], result["n_pairs"]) == (1.0, None, 3)


def test_ties_between_depths_follow_the_particles_size():
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.calibrate import LARGE_PARTICLE_PX, calibrate_split, median_diameter, tied_best

    rows = [
        {"split_depth": 2.0, "split_core": None, "ap50": 0.9051},
        {"split_depth": 4.0, "split_core": None, "ap50": 0.8800},
        {"split_depth": 8.0, "split_core": None, "ap50": 0.9040},  # within TIE (0.002) of the best
        {"split_depth": 8.0, "split_core": 0.7, "ap50": 0.9048},
        {"split_depth": 16.0, "split_core": None, "ap50": 0.8900},
    ]
    assert tied_best(rows, 25.0) is rows[0]  # small particles: the smaller tied depth (fewer merges)
    assert tied_best(rows, LARGE_PARTICLE_PX) is rows[2]  # large: the larger depth, its first (most lenient) core
    assert tied_best(rows, float("nan")) is rows[0]
    assert tied_best([{"seed_level": 0.3, "ap50": 0.5}, {"seed_level": 0.4, "ap50": 0.5}], 300.0)["seed_level"] == 0.3
    # equivalent-circle diameters: a 10 x 10 square (d = 11.28) and a 4 x 4 square (4.51), median of two
    labels = np.zeros((20, 20), np.int32)
    labels[:10, :10], labels[12:16, 12:16] = 1, 2
    assert median_diameter([labels]) == pytest.approx((2 * np.sqrt(100 / np.pi) + 2 * np.sqrt(16 / np.pi)) / 2)
    assert np.isnan(median_diameter([np.zeros((4, 4), np.int32)]))
    # calibrate_split measures the validation particles' size and records it with the choice
    apart = _pair(_two_touching_discs(r=7.0, gap=20.0))
    result = calibrate_split(ProbabilityImage(), [apart], {"cores": [None], "depths": [1.0, 2.0]}, tile=48)
    truth = median_diameter([binarize_and_label(apart.mask)])
    assert result["particle_px"] == pytest.approx(truth) and 10 < truth < 15  # two r = 7 discs, contour removed


@pytest.mark.parametrize(
    "grid, message",
    [
        ({"cores": [1.0]}, "cores: 1.0 is not a particle probability"),
        ({"depths": [0]}, "depths: 0 is not a positive depth"),
        ({"cores": []}, "at least one value"),
        ({"max_pairs": 0}, "max_pairs: 0"),
        ({"core": [0.5]}, "unknown key"),
        ({"seeds": ["peaks"]}, "seeds"),
        ({"objective": "dsc"}, "objective"),
    ],
)
def test_bad_grids_are_config_errors_naming_the_entry(grid, message):
    from drgan.segmenters.calibrate import check_grid

    with pytest.raises(ConfigError, match=message):
        check_grid(grid)
    assert check_grid(None) is None


def test_auto_settings_come_from_the_checkpoint_or_the_uncalibrated_defaults(tmp_path, caplog):
    from drgan.core.checkpoint_io import add_entry
    from drgan.segmenters.calibrate import CHECKPOINT_KEY, UNCALIBRATED, resolve_auto, stored_split

    path = tmp_path / "x.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, path)
    calibration = {"split_depth": 2.0, "split_core": 0.8, "n_pairs": 7}
    add_entry(path, CHECKPOINT_KEY, calibration)
    loaded = torch.load(path, weights_only=True)
    assert torch.equal(loaded["state_dict"]["w"], torch.zeros(2)) and stored_split(loaded) == calibration
    assert not list(tmp_path.glob(".*partial"))  # written whole, renamed into place

    inference = {"tile": 32, "split_depth": "auto", "split_core": "auto"}
    assert resolve_auto(inference, calibration) == (
        {"tile": 32, "split_depth": 2.0, "split_core": 0.8},
        "calibrated on 7 validation pairs",
    )
    settings, note = resolve_auto(inference, None, "model=old.ckpt")
    assert settings == {"tile": 32, "split_depth": 1.0, "split_core": 0.95} and note == "uncalibrated defaults"
    # the instance-aware segmenter's seed level: its calibration's, else 0.5
    centres = {"split": "centres", "seed_level": 0.4, "split_depth": 1.0, "split_core": 0.95, "n_pairs": 3}
    assert resolve_auto({"seed_level": "auto"}, centres)[0] == {"seed_level": 0.4}
    assert resolve_auto({"seed_level": "auto"}, calibration)[0] == {"seed_level": UNCALIBRATED["seed_level"]}
    assert "model=old.ckpt" in caplog.text and "no split calibration" in caplog.text
    fixed = {"split_depth": 3.0, "split_core": None}
    assert resolve_auto(fixed, calibration) == (fixed, "")  # numbers given are kept
    assert stored_split({CHECKPOINT_KEY: {"split_depth": -1}}) is None  # malformed: ignored, with a warning


def test_segment_yaml_grid_is_the_calibration_default():
    """segment.yaml's split_calibration (what users read and change) and GRID_DEFAULTS (what a checkpoint is
    recalibrated with) are one grid."""
    from omegaconf import OmegaConf

    from drgan.launch.configs import compose
    from drgan.segmenters.calibrate import GRID_DEFAULTS, check_grid

    grid = OmegaConf.to_container(compose(["data=D"], config_name="segment").split_calibration)
    assert check_grid(grid) == check_grid(GRID_DEFAULTS) and grid == GRID_DEFAULTS


def test_every_core_piece_the_contour_cut_off_keeps_a_seed():
    from drgan.metrics.instance_scores import binarize_and_label
    from drgan.segmenters.inference import split_touching

    # a small particle (r 3.5) touching a large one (r 8): its core's dome is lower than the h-maxima depth of 2 px, so
    # it gets no seed and the large one's flood takes it (one merged particle); every piece keeps a seed: both exact
    yy, xx = np.mgrid[:32, :32]
    labels = np.zeros((32, 32), np.int32)
    labels[(yy - 16) ** 2 + (xx - 11) ** 2 <= 8**2] = 1
    labels[((yy - 16) ** 2 + (xx - 22.5) ** 2 <= 3.5**2) & (labels == 0)] = 2
    classes = class_mask(labels, 1)
    probs = np.stack([(classes == c).astype(np.float32) for c in range(3)])
    merged = binarize_and_label(split_touching(probs, 2.0, 1.0, None, "hmaxima"))
    apart = binarize_and_label(split_touching(probs, 2.0, 1.0, None, "components"))
    assert merged.max() == 1 and (merged > 0).sum() == (labels > 0).sum()
    assert apart.max() == 2 and sorted(np.bincount(apart.ravel())[1:]) == [(labels == 2).sum() - 1, (labels == 1).sum()]
    with pytest.raises(ConfigError, match="split_seeds"):
        split_touching(probs, 2.0, 1.0, None, "peaks")


def test_the_calibration_scores_against_exact_labels_where_the_pairs_carry_them():
    from drgan.segmenters.calibrate import calibrate_split

    labels = _two_touching_discs(r=7.0, gap=20.0)
    plain = _pair(labels)
    exact = Pair("p", plain.image, plain.mask, labels)
    grid = {"cores": [None], "depths": [1.0], "seeds": ["hmaxima", "components"]}
    with_labels = calibrate_split(ProbabilityImage(), [exact], grid, tile=48)
    without = calibrate_split(ProbabilityImage(), [plain], grid, tile=48)
    # the particle's whole extent (its contour rim included) against the particle class alone: 2 px wider
    assert with_labels["particle_px"] == pytest.approx(without["particle_px"] + 2.0, abs=0.6)
    assert [row["split_seeds"] for row in with_labels["table"]] == ["hmaxima", "components"]
    assert with_labels["split_seeds"] == "hmaxima"  # a tie keeps the first rule


def test_the_sizes_objective_takes_the_nearest_sizes_within_the_ap50_margin():
    from drgan.segmenters.calibrate import SIZES_AP50_MARGIN, sizes_best

    rows = [
        {"split_depth": 1.0, "split_core": None, "ap50": 0.60, "median_error": 0.30, "count_error": -0.30},
        {"split_depth": 2.0, "split_core": None, "ap50": 0.60 - SIZES_AP50_MARGIN / 2, "median_error": 0.05,
         "count_error": -0.10},
        {"split_depth": 4.0, "split_core": None, "ap50": 0.40, "median_error": 0.0, "count_error": 0.0},
    ]  # fmt: skip
    assert sizes_best(rows, 20.0) is rows[1]  # the exact third gives up too much detection
    unknown = [{**row, "median_error": None} for row in rows]
    assert sizes_best(unknown, 20.0) is unknown[0]  # no sizes to compare: by AP50 alone


def test_calibrate_split_records_the_sizes_of_every_setting_and_chooses_by_the_objective():
    from drgan.segmenters.calibrate import calibrate_split

    pair = _pair(_two_touching_discs(r=10.0, gap=7.0), neck_probability=0.6)
    exact = Pair("p", pair.image, pair.mask, _two_touching_discs(r=10.0, gap=7.0))
    grid = {"cores": [None, 0.7], "depths": [2.0], "seeds": ["hmaxima"], "objective": "sizes"}
    result = calibrate_split(ProbabilityImage(), [exact, exact], grid, tile=48)
    merged, apart = result["table"]
    assert merged["count_error"] == -0.5 and apart["count_error"] == 0.0  # one blob for two discs; both found
    assert result["split_core"] == 0.7 and result["objective"] == "sizes" and result["count_error"] == 0.0


def _pairs_of_discs(size=96, r1=9.0, r2=7.0, gap=14.0):
    """Four pairs of overlapping discs of radii ``r1`` and ``r2`` (centres ``gap`` apart: the smaller one's distance
    peak stands between 1 and 4 px above the neck, so a split depth of 1 px cuts the neck and one of 4 px does not),
    as classical instance labels (each disc its own id) and as a particle probability image (0.95 inside, 0.02 out)."""
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    k = 0
    for cy in (24, 72):
        for cx in (24, 72):
            for r, dx in ((r1, -gap / 2), (r2, gap / 2)):
                k += 1
                labels[((yy - cy) ** 2 + (xx - cx - dx) ** 2 <= r * r) & (labels == 0)] = k
    return labels, np.where(labels > 0, 0.95, 0.02).astype(np.float32)


def test_the_real_count_guard_keeps_a_choice_near_the_classical_count_and_moves_one_that_merges():
    from types import SimpleNamespace

    from drgan.segmenters.calibrate import REAL_COUNT_CEILING, REAL_COUNT_GUARD, real_count_guard

    labels, probs = _pairs_of_discs()
    items = [(SimpleNamespace(image=probs, id="a"), labels)]
    row = lambda depth, ap50: {"split_seeds": "hmaxima", "split_depth": depth, "split_core": None, "ap50": ap50,  # noqa: E731
                               "median_error": 0.01 * depth, "count_error": -0.01 * depth}  # fmt: skip
    table = [row(1.0, 0.80), row(4.0, 0.77), row(16.0, 0.50)]  # depth 16: outside the 0.05 AP50 margin
    calibration = {"split": "watershed", "split_smooth": 1.0, "objective": "sizes", "table": table, **table[1]}
    model = ProbabilityImage()
    moved = real_count_guard(model, calibration, items)
    # depth 4 takes each pair for one particle: 4 against the classical 8 (-50 %); depth 1 cuts every neck
    guard = moved["real_count"]
    assert (guard["classical"], guard["chosen_count"], guard["count"], guard["moved"]) == (8, 4, 8, True)
    assert moved["split_depth"] == 1.0 and moved["ap50"] == 0.80 and moved["median_error"] == 0.01
    assert guard["from"] == {"split_seeds": "hmaxima", "split_depth": 4.0, "split_core": None}
    # the choice that counts as the classical segmentation does stays, its calibration untouched but for the record
    kept = real_count_guard(model, {**calibration, **table[0]}, items)
    assert not kept["real_count"]["moved"] and kept["split_depth"] == 1.0 and kept["real_count"]["count"] == 8
    # the classical count is a floor, not a target: a choice that finds more particles than it stays (classical labels
    # that merge every pair: 4 against depth 1's 8)
    pairs_merged = np.where(labels > 0, (labels + 1) // 2, 0)
    above = real_count_guard(model, {**calibration, **table[0]}, [(items[0][0], pairs_merged)])
    assert above["real_count"]["classical"] == 4 and not above["real_count"]["moved"] and above["split_depth"] == 1.0
    # ... up to REAL_COUNT_CEILING times it (8 against 4 is twice, kept); beyond, the choice cuts particles apart and
    # the setting counting the most under the ceiling is taken: classical labels of 3 particles (two pairs one id),
    # depth 1's 8 over the ceiling of 6, depth 4's 4 under it
    assert REAL_COUNT_CEILING == 2.0
    three = np.where(pairs_merged == 4, 3, pairs_merged)
    cut = real_count_guard(model, {**calibration, **table[0]}, [(items[0][0], three)])
    guard = cut["real_count"]
    assert (guard["classical"], guard["chosen_count"], guard["count"], guard["side"]) == (3, 8, 4, "above")
    assert guard["moved"] and guard["ceiling"] == 6.0 and cut["split_depth"] == 4.0 and cut["ap50"] == 0.77
    assert [(c["split_depth"], c["count"]) for c in guard["counts"]] == [(1.0, 8), (4.0, 4)]  # the margin's settings
    # classical labels that split one disc more (9) leave depth 1 11 % below, the nearest there is: depth 1 kept
    assert REAL_COUNT_GUARD == 0.10
    more = labels.copy()
    more[(more == 1) & (np.arange(96)[None, :] < 14)] = 99  # the first disc's left part a particle of its own
    near = real_count_guard(model, {**calibration, **table[0]}, [(items[0][0], more)])
    assert near["real_count"]["classical"] == 9 and not near["real_count"]["moved"]
    # an instance-aware segmenter's seed levels, or no real images: the calibration as it was
    assert real_count_guard(model, {**calibration, "split": "centres"}, items) == {**calibration, "split": "centres"}
    assert real_count_guard(model, calibration, []) is calibration


def test_segment_calibrate_stores_its_choice_only_when_asked(tmp_path):
    """drgan.segment's calibration writes the chosen split into the checkpoint evaluate and analyze read; with
    ``store=False`` (recalibrate.py's dry run) it chooses the same split and leaves the file as it was."""
    from drgan.core.checkpoint_io import load_checkpoint
    from drgan.segment import calibrate
    from drgan.segmenters.calibrate import CHECKPOINT_KEY

    last = tmp_path / "last.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(2)}}, last)
    before = last.read_bytes()
    pair = _pair(_two_touching_discs(r=10.0, gap=7.0), neck_probability=0.6)
    grid = {"cores": [None, 0.7], "depths": [2.0], "seeds": ["hmaxima"], "objective": "ap50"}
    dry = calibrate(ProbabilityImage(), [pair, pair], grid, last, progress=False, store=False)
    assert last.read_bytes() == before and (dry["split_core"], dry["ap50"]) == (0.7, 1.0)
    stored = calibrate(ProbabilityImage(), [pair, pair], grid, last, progress=False)
    assert load_checkpoint(last, "ckpt")[CHECKPOINT_KEY] == stored and stored["split_core"] == dry["split_core"]
