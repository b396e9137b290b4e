"""The closed-loop check: a segmenter measured on held-out generated pairs against their exact outlines."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from drgan.scene.labels import IGNORE, class_mask
from drgan.segmenters.closed_loop import closed_loop, hold_out, stored_closed_loop, trust_line
from drgan.segmenters.pairs import Pair

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def squares(n=3, side=10, size=64, gap=8) -> np.ndarray:
    """n separate side x side squares in a row (ids 1..n), none touching another or the border."""
    labels = np.zeros((size, size), np.int32)
    for k in range(n):
        x = gap + k * (side + gap)
        labels[gap : gap + side, x : x + side] = k + 1
    return labels


def pair_of(labels: np.ndarray, name="p") -> Pair:
    image = np.where(labels > 0, 0.8, 0.2).astype(np.float32)
    return Pair(name, image, class_mask(labels, 1), labels)


def exact(labels_of):
    """A predictor returning the exact particles as the particle class."""
    return lambda image: (labels_of[id(image)] > 0).astype(np.uint8)


def run(pairs, transform=lambda labels: labels > 0):
    by_image = {id(p.image): p.labels for p in pairs}
    return closed_loop(None, pairs, predictor=lambda image: transform(by_image[id(image)]).astype(np.uint8), n_boot=50)


def test_a_predictor_returning_the_exact_labels_scores_no_error():
    pairs = [pair_of(squares(n=k + 1), f"p{k}") for k in range(4)]
    check = run(pairs)
    assert check["median_error"]["value"] == 0.0 and check["mean_error"]["value"] == 0.0
    assert check["count_error"]["value"] == 0.0 and check["count_error"]["low"] == 0.0
    assert check["diameter_offset_px"] == 0.0 and check["edge_offset_px"] == 0.0
    assert check["matched"] == 1.0 and check["merged"] == check["split"] == check["missed"] == 0.0
    assert check["ap50"] == 1.0 and check["dsc"] == 1.0 and check["n_true"] == 10 and check["n_pairs"] == 4
    assert json.loads(json.dumps(check)) == check  # plain numbers: JSON and weights_only checkpoints take them


def test_a_one_pixel_dilation_gives_the_offset_computed_by_hand():
    # a 10 x 10 square grown by the 4-neighbour cross: 12 x 12 less its 4 corners = 140 px
    grow = lambda labels: ndimage.binary_dilation(labels > 0)  # noqa: E731
    check = run([pair_of(squares(n=3))], grow)
    d_true, d_pred = 2 * math.sqrt(100 / math.pi), 2 * math.sqrt(140 / math.pi)
    assert check["diameter_offset_px"] == pytest.approx(d_pred - d_true)
    assert check["edge_offset_px"] == pytest.approx((d_pred - d_true) / 2)
    assert check["median_error"]["value"] == pytest.approx(d_pred / d_true - 1)  # sqrt(1.4) - 1: +18.3 %
    assert check["count_error"]["value"] == 0.0 and check["matched"] == 1.0


def test_the_check_draws_what_it_counted_found_green_false_red_missed_yellow(tmp_path):
    from drgan.metrics.overlays import GREEN, RED, YELLOW

    labels = squares(n=3)  # the predictor finds squares 1 and 2, misses 3 and adds a false one

    def found(image):
        pred = np.isin(labels, [1, 2]).astype(np.uint8)
        pred[50:56, 2:8] = 1
        return pred

    pairs = [pair_of(labels, f"p{k}") for k in range(30)]
    check = closed_loop(None, pairs, predictor=found, n_boot=10, sheet=tmp_path / "closed_loop.png")
    assert check["missed"] == pytest.approx(1 / 3) and check["false"] == pytest.approx(1 / 3)
    drawn = np.asarray(Image.open(tmp_path / "closed_loop.png").convert("RGB"))
    # 24 of the 30 pairs, 64-px cells under a 12-px caption, in rows of 6 with 4-px gaps: 4 rows
    assert drawn.shape == (4 * (12 + 64) + 3 * 4, 6 * 64 + 5 * 4, 3)
    top, left = 12 + 64 + 4, 64 + 4  # the second row's second pair, p7
    cell = drawn[top + 12 : top + 12 + 64, left : left + 64].astype(np.int64)
    blend = lambda grey, colour: np.round(0.5 * round(grey * 255) + 0.5 * np.array(colour))  # noqa: E731
    np.testing.assert_array_equal(cell[labels == 1][0], blend(0.8, GREEN))
    np.testing.assert_array_equal(cell[labels == 3][0], blend(0.8, YELLOW))
    np.testing.assert_array_equal(cell[52, 4], blend(0.2, RED))
    np.testing.assert_array_equal(cell[0, 0], [51, 51, 51])  # background untouched (0.2 grey)
    caption = drawn[top : top + 12, left : left + 64]
    assert (caption < 128).any() and (caption == 255).mean() > 0.5  # dark text on white: the pair's id
    assert (drawn[12 + 64 : 12 + 64 + 4] == 255).all()  # the gap between rows


def test_the_checks_picture_shows_pairs_with_particles_before_particle_free_ones(tmp_path):
    from drgan.metrics.overlays import GREEN

    empty, full = np.zeros((64, 64), np.int32), squares(n=2)
    pairs = [pair_of(empty, "bg0"), pair_of(full, "p0"), pair_of(empty, "bg1"), pair_of(full, "p1")]
    run_pairs = {id(p.image): p.labels for p in pairs}
    closed_loop(None, pairs, predictor=lambda im: run_pairs[id(im)] > 0, n_boot=5, sheet=tmp_path / "c.png")
    drawn = np.asarray(Image.open(tmp_path / "c.png").convert("RGB")).astype(np.int64)
    cells = [drawn[12 : 12 + 64, k * 68 : k * 68 + 64] for k in range(4)]
    green = np.round(0.5 * round(0.8 * 255) + 0.5 * np.array(GREEN))
    holds = [bool((cell == green).all(axis=-1).any()) for cell in cells]
    assert holds == [True, True, False, False]  # p0, p1, then bg0, bg1


def test_a_sheets_captions_are_the_tiles_ids_and_must_match_them():
    from drgan.metrics.overlays import CAPTION_PX, sheet

    tiles = [np.zeros((20, 30, 3), np.uint8)] * 3
    plain, captioned = sheet(tiles, columns=3), sheet(tiles, columns=3, captions=["a", "bb", ""])
    assert captioned.shape == (plain.shape[0] + CAPTION_PX, plain.shape[1], 3)
    np.testing.assert_array_equal(captioned[CAPTION_PX:], plain)  # the tiles below their strips, as without
    strips = [captioned[:CAPTION_PX, k * 34 : k * 34 + 30] for k in range(3)]
    assert (strips[0] < 128).any() and (strips[1] < 128).sum() > (strips[0] < 128).sum()  # two letters, more ink
    assert (strips[2] == 255).all()  # no caption, no ink
    with pytest.raises(ValueError, match="2 captions for 3 tiles"):
        sheet(tiles, captions=["a", "b"])


def test_touching_particles_predicted_as_one_are_counted_as_merged():
    labels = np.zeros((64, 64), np.int32)
    labels[8:18, 8:18], labels[8:18, 18:28], labels[8:18, 40:50] = 1, 2, 3  # 1 and 2 touch
    merged = lambda lab: lab > 0  # noqa: E731  (one 4-connected region for the touching two)
    check = run([pair_of(labels)], merged)
    assert check["count_error"]["value"] == pytest.approx(2 / 3 - 1)
    assert check["merged"] == pytest.approx(2 / 3) and check["matched"] == pytest.approx(1 / 3)


def test_the_check_says_which_contacts_it_merged_those_the_image_hides_or_those_it_shows():
    """Two touching pairs: one whose contact is as bright as the particles (hidden), one whose contact falls to the
    background (shown); the predictor merges the first and cuts the second."""
    from drgan.data.necks import contact_pairs

    labels = np.zeros((64, 64), np.int32)
    labels[8:18, 8:18], labels[8:18, 18:28] = 1, 2
    labels[40:50, 8:18], labels[40:50, 18:28] = 3, 4
    pair = pair_of(labels)
    pair.image[contact_pairs(labels)[0] & (labels >= 3)] = 0.2  # the second contact shows as background
    merged = np.where(labels == 2, 1, labels)  # 1 and 2 as one particle, 3 and 4 apart (a contour between them)
    check = closed_loop(None, [pair], predictor=lambda image: class_mask(merged, 1), n_boot=20)
    assert check["contacts"] == {"n": 2, "hidden": 0.5, "hidden_merged": 1.0, "shown_merged": 0.0}
    assert "merged 100 % of the touching pairs whose contact the image hides (50 % of 2) and 0 % of those it shows" in (
        trust_line(check)
    )
    assert "contact" not in trust_line({**check, "contacts": None})


def test_the_check_pairs_are_rendered_ones_seeded_and_never_most_of_the_set():
    rendered = [pair_of(squares(), f"r{k}") for k in range(40)]
    partial = Pair("bg", rendered[0].image, np.full((64, 64), IGNORE, np.uint8), rendered[0].labels)
    handmade = Pair("hand", rendered[0].image, rendered[0].mask, None)
    pairs = [*rendered, partial, handmade]
    rest, check = hold_out(pairs, 0.1, seed=3)
    assert len(check) == 4 and {p.id for p in check} <= {p.id for p in rendered}
    assert len(rest) + len(check) == len(pairs) and not {p.id for p in rest} & {p.id for p in check}
    assert [p.id for p in hold_out(pairs, 0.1, seed=3)[1]] == [p.id for p in check]
    assert hold_out(pairs, 0.0, seed=3) == (pairs, [])
    assert hold_out(rendered[:10], 0.05, seed=0) == (rendered[:10], [])  # 4 of 10 would be too many
    with pytest.raises(Exception, match="check_fraction"):
        hold_out(pairs, 0.7, seed=0)


def test_the_trust_line_quotes_the_errors_with_their_intervals():
    check = run([pair_of(squares(n=k + 1), f"p{k}") for k in range(3)], lambda lab: ndimage.binary_dilation(lab > 0))
    line = trust_line(check)
    assert "3 generated images" in line and "6 particles" in line
    assert "median diameter is off by +18.3 % [+18.3 %, +18.3 %]" in line and "count by +0.0 %" in line
    assert f"{check['edge_offset_px']:+.2f} px" in line


def make_labelled_set(folder: Path, n=24, size=32) -> Path:
    """Rendered-style pairs with their exact instance labels (labels/), as drgan.generate writes them."""
    from test_segment import disc_image, disc_labels

    for d in ("images", "masks", "labels"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        labels = disc_labels(size, seed=i)
        Image.fromarray((disc_image(labels, i) * 255).astype(np.uint8)).save(folder / "images" / f"{i:03d}.png")
        Image.fromarray(class_mask(labels, 1)).save(folder / "masks" / f"{i:03d}.png")
        Image.fromarray(labels.astype(np.uint8)).save(folder / "labels" / f"{i:03d}.png")
    return folder


def test_segment_scores_itself_on_held_out_pairs_and_stores_the_check(tmp_path):
    import torch
    from conftest import compose
    from test_segment import tiny_segment_overrides

    from drgan.segment import segment
    from drgan.segmenters.module import load_segmenter

    data = make_labelled_set(tmp_path / "gen")
    out = tmp_path / "run"
    overrides = tiny_segment_overrides(data, tmp_path, out, "trainer.max_epochs=1", "check_fraction=0.2")
    metrics = segment(compose(overrides, config_name="segment"))
    written = json.loads((out / "metrics.json").read_text())
    check = written["closed_loop"]
    assert check["n_pairs"] == 5 and check["n_true"] > 0  # 0.2 of 24, never trained on
    assert {"check/count_error", "check/ap50"} <= set(metrics)  # a 1-epoch net may size no particle: no median
    assert metrics["check/count_error"] == pytest.approx(check["count_error"]["value"])
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert stored_closed_loop(ckpt) == check
    assert load_segmenter(out / "checkpoints" / "last.ckpt").closed_loop == check
    assert Image.open(out / "closed_loop.png").size[1] >= 16  # the check's picture beside its numbers
    # resuming a finished run checks again on the same held-out pairs and keeps its last validation score
    segment(compose([*overrides, "ckpt_path=last"], config_name="segment"))
    again = json.loads((out / "metrics.json").read_text())
    assert again["closed_loop"]["ids"] == check["ids"] and again["val/dsc"] == written["val/dsc"]
    # analyze's statistics.md quotes the check; the pipeline's report compares its sizes with the classical ones
    from drgan.analyze import AnalyzeSettings, analyze

    last = out / "checkpoints" / "last.ckpt"
    cfg = compose([f"model={last}", f"images={data / 'images'}", f"out={tmp_path / 'an'}", "bootstrap=0"], "analyze")
    analyze(AnalyzeSettings.from_config(cfg))
    assert trust_line(check) in (tmp_path / "an" / "statistics.md").read_text()
    assert json.loads((tmp_path / "an" / "summary.json").read_text())["closed_loop"] == check


def check_of(value, low, high) -> dict:
    return {"median_error": {"value": value, "low": low, "high": high}}


def test_the_report_says_when_the_segmenter_and_the_classical_sizes_disagree_and_which_it_trusts():
    from drgan.segmenters.classical_check import compare_with_classical

    exact = check_of(0.01, -0.01, 0.03)
    agree = compare_with_classical(51.0, 50.0, exact)
    assert "+2.0 %" in agree and "agree" in agree and "trusts these sizes" in agree
    # a 16 % gap, beyond the interval widened by 5 %: the exact segmenter is trusted, the user is told to compare
    apart = compare_with_classical(58.0, 50.0, exact)
    assert "+16.0 %" in apart and "beyond the closed-loop interval" in apart and "trusts the segmenter" in apart
    # a segmenter biased by +20 % on exact truth, 16 % above the classical sizes: its bias explains the gap
    biased = compare_with_classical(58.0, 50.0, check_of(0.20, 0.15, 0.25))
    assert "what the closed-loop check predicts" in biased and "trusts the classical sizes" in biased
    merged = compare_with_classical(58.0, 50.0, {**check_of(0.20, 0.15, 0.25), "merged": 0.069, "edge_offset_px": 0.0})
    assert "(6.9 % of the generated particles merged with a neighbour)." in merged
    wide = compare_with_classical(58.0, 50.0, {**check_of(0.20, 0.15, 0.25), "merged": 0.01, "edge_offset_px": 1.2})
    assert "(its outlines +1.20 px from the true edge)." in wide
    # biased on generated images, yet within 5 % of the classical sizes (tio2_tsem: +14 % on piled generated scenes,
    # -2 % from the classical, +0.8 % on the annotated test ids): the agreement of two methods is trusted
    both = compare_with_classical(49.0, 50.0, {**check_of(0.144, 0.076, 0.274), "merged": 0.219})
    assert "-2.0 %" in both and "agree within 5 %" in both and "21.9 % of their particles merged" in both
    assert "trusts these sizes" in both
    # biased and beyond its own bias: neither
    assert "Neither is trusted" in compare_with_classical(80.0, 50.0, check_of(0.20, 0.15, 0.25))
    assert "without a closed-loop check" in compare_with_classical(58.0, 50.0, None)
    assert "missing" in compare_with_classical(None, 50.0, exact)


def test_the_rendered_pairs_contour_is_redrawn_from_their_labels_and_ignored_pixels_stay_ignored():
    from drgan.segment import redrawn_contours

    labels = np.zeros((64, 64), np.int32)
    labels[8:18, 8:18], labels[8:18, 18:28] = 1, 2
    rendered = pair_of(labels, "r")
    rendered.mask[0:4, 0:4] = IGNORE
    handmade = Pair("h", rendered.image, class_mask(labels, 1), None)
    wide, kept = redrawn_contours([rendered, handmade], 3)
    expected = class_mask(labels, 3)
    expected[0:4, 0:4] = IGNORE
    np.testing.assert_array_equal(wide.mask, expected)
    assert (wide.mask == 2).sum() > (class_mask(labels, 1) == 2).sum()  # a wider line between the touching two
    assert kept is handmade and redrawn_contours([rendered], None) == [rendered]


def test_the_pipeline_report_quotes_the_check_and_compares_with_the_profile(tmp_path):
    from drgan.pipeline.report import analyze_details, analyze_summary

    check = {**check_of(0.01, -0.01, 0.03), "count_error": {"value": -0.02, "low": -0.04, "high": 0.0}}
    check.update(n_pairs=50, n_true=300, edge_offset_px=0.1, merged=0.02)
    (tmp_path / "analyze").mkdir()
    (tmp_path / "profile").mkdir()
    summary = {"images": 3, "unit": "px", "statistics": {}, "median_diameter_px": 58.0, "closed_loop": check}
    (tmp_path / "analyze" / "summary.json").write_text(json.dumps(summary))
    (tmp_path / "profile" / "profile.json").write_text(json.dumps({"sizes": {"median_diameter_px": 50.0}}))
    lines = analyze_details(analyze_summary(tmp_path / "analyze"), None)
    assert lines[0] == f"- how far these sizes can be trusted: {trust_line(check)}"
    assert "+16.0 %" in lines[1] and "beyond the closed-loop interval" in lines[1]
    summary.pop("closed_loop")
    (tmp_path / "analyze" / "summary.json").write_text(json.dumps(summary))
    assert "no closed-loop check" in analyze_details(analyze_summary(tmp_path / "analyze"), None)[0]


def test_a_bad_check_fraction_is_refused_before_any_pair_is_read(tmp_path):
    from conftest import compose
    from test_segment import tiny_segment_overrides

    from drgan.core.errors import ConfigError
    from drgan.segment import segment

    cfg = compose(
        tiny_segment_overrides(tmp_path / "missing", tmp_path, tmp_path / "o", "check_fraction=0.6"), "segment"
    )
    with pytest.raises(ConfigError, match="check_fraction=0.6"):
        segment(cfg)
    assert not (tmp_path / "o").exists()


def test_a_segmenter_at_an_enlarged_working_scale_is_checked_on_its_pairs_as_rendered(tmp_path):
    """loader.min_working_px: the training pairs enlarged, the closed-loop pairs held out at the rendered scale and
    resampled by the working scale as a real image is; the same ids held out as without enlarging."""
    from conftest import compose
    from test_segment import tiny_segment_overrides

    from drgan.segment import segment
    from drgan.segmenters.pairs import load_generated_pairs, sample_diameters

    data = make_labelled_set(tmp_path / "gen")
    median = float(np.median(sample_diameters(load_generated_pairs(data))))
    checks = {}
    for name, extra in (("plain", []), ("enlarged", [f"loader.min_working_px={2 * median}"])):
        overrides = tiny_segment_overrides(data, tmp_path, tmp_path / name, "trainer.max_epochs=1", "check_fraction=0.2",
                                           "logger=none", "split_calibration=null", *extra)  # fmt: skip
        segment(compose(overrides, config_name="segment"))
        checks[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    plain, enlarged = checks["plain"], checks["enlarged"]
    assert enlarged["pixel_scale"] == pytest.approx(2.0) and plain["pixel_scale"] == 1.0
    assert enlarged["closed_loop"]["ids"] == plain["closed_loop"]["ids"]
    truth = [c["closed_loop"]["median_diameter_true_px"] for c in (plain, enlarged)]
    assert truth[1] == pytest.approx(truth[0]) and truth[0] == pytest.approx(median, rel=0.25)
