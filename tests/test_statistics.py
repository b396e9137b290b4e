"""Particle statistics against the truth (drgan.metrics.statistics, drgan.evaluate's statistics): exact values on
hand-made label images, and the distances against scipy and scikit-image."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import ks_2samp, wasserstein_distance
from test_segment import disc_image, disc_labels, eval_cfg, make_real

from drgan.metrics.statistics import compare_sizes, count_errors, ks_statistic, particles, pooled, wasserstein1


def squares(size: int, boxes) -> np.ndarray:
    """A label image of axis-aligned rectangles (r0, c0, height, width), label k + 1 for box k."""
    labels = np.zeros((size, size), np.int32)
    for k, (r, c, h, w) in enumerate(boxes):
        labels[r : r + h, c : c + w] = k + 1
    return labels


def test_particles_of_hand_made_labels_are_exact():
    labels = squares(40, [(5, 5, 4, 4), (20, 10, 6, 12), (0, 30, 5, 5)])  # the last one touches the top border
    found = particles(labels)
    assert found.count == 3
    np.testing.assert_array_equal(found.area, [16, 72, 25])
    np.testing.assert_allclose(found.diameter, 2 * np.sqrt(np.array([16, 72, 25]) / np.pi))
    np.testing.assert_array_equal(found.border, [False, False, True])
    # A w x h block's pixel-centre variances are (w^2 - 1) / 12 and (h^2 - 1) / 12: axis ratio sqrt of their ratio.
    assert found.axis_ratio[1] == pytest.approx(np.sqrt((12**2 - 1) / (6**2 - 1)))
    assert found.axis_ratio[0] == pytest.approx(1.0)
    whole = found.whole()
    assert whole.count == 2 and set(whole.area) == {16, 72}
    # The same numbers as scikit-image's regionprops, computed independently of the module's loop.
    from skimage.measure import regionprops

    assert [r.equivalent_diameter_area for r in regionprops(labels)] == pytest.approx(list(found.diameter))


def test_sizes_and_counts_of_a_hand_made_prediction_are_exact():
    true = [particles(squares(50, [(5, 5, 10, 10), (20, 20, 10, 10)])), particles(squares(50, [(30, 5, 10, 10)]))]
    # Image 1: both found, one 20 % wider; image 2: the particle found plus a false one cut by the border.
    pred = [
        particles(squares(50, [(5, 5, 10, 10), (20, 20, 10, 12)])),
        particles(squares(50, [(30, 5, 10, 10), (0, 40, 3, 3)])),
    ]
    stats = compare_sizes(pred, true, n_boot=0)
    d10, d_wide = 2 * np.sqrt(100 / np.pi), 2 * np.sqrt(120 / np.pi)
    assert stats["median_diameter_true"]["value"] == pytest.approx(d10)
    assert stats["median_diameter"]["value"] == pytest.approx(d10)  # the border particle is not sized
    assert stats["mean_error"]["value"] == pytest.approx((2 * d10 + d_wide) / (3 * d10) - 1)
    assert stats["count_error"]["value"] == pytest.approx(4 / 3 - 1)  # the cut particle counts
    np.testing.assert_array_equal(count_errors(pred, true), [0, 1])
    assert stats["ks"]["value"] == pytest.approx(1 / 3)
    assert stats["w1"]["value"] == pytest.approx((d_wide - d10) / 3)
    assert len(pooled(true)) == 3 and np.isnan(stats["median_error"]["low"])  # no bootstrap asked


def test_specks_below_the_minimum_area_are_neither_counted_nor_sized():
    # a 1-px speck, a 2 x 2 and a 2 x 4 blob (4 and 8 px^2), a 10 x 10 particle, a 1-px speck on the border
    found = particles(squares(40, [(3, 3, 1, 1), (10, 3, 2, 2), (20, 3, 2, 4), (20, 20, 10, 10), (0, 39, 1, 1)]))
    kept = found.at_least(8)
    assert kept.count == 2 and list(kept.area) == [8, 100] and not kept.border.any()
    assert found.at_least(0).count == 5 and found.at_least(101).count == 0
    # Both sides alike: a prediction without the truth's specks is exact once they are left out on both.
    true = [found]
    pred = [particles(squares(40, [(20, 3, 2, 4), (20, 20, 10, 10)]))]
    assert compare_sizes(pred, true, n_boot=0)["count_error"]["value"] == pytest.approx(2 / 5 - 1)
    exact = compare_sizes([p.at_least(8) for p in pred], [t.at_least(8) for t in true], n_boot=0)
    assert exact["count_error"]["value"] == 0 and exact["median_error"]["value"] == 0


def test_distances_equal_scipys():
    rng = np.random.default_rng(0)
    for n, m in ((5, 7), (40, 40), (100, 13)):
        a, b = rng.lognormal(3.0, 0.4, n), rng.lognormal(3.1, 0.3, m)
        assert ks_statistic(a, b) == pytest.approx(ks_2samp(a, b).statistic)
        assert wasserstein1(a, b) == pytest.approx(wasserstein_distance(a, b))
    ties = np.array([1.0, 1.0, 2.0, 3.0])
    assert ks_statistic(ties, ties[:3]) == pytest.approx(ks_2samp(ties, ties[:3]).statistic)
    assert np.isnan(ks_statistic([], [1.0])) and np.isnan(wasserstein1([1.0], []))


def test_bootstrap_intervals_cover_the_value_and_collapse_when_nothing_differs():
    true = [particles(disc_labels(64, n=6, radius=r, seed=s)) for s, r in enumerate((4.0, 5.0, 6.0, 5.5, 4.5))]
    same = compare_sizes(true, true, n_boot=200, seed=1)
    for key in ("median_error", "count_error", "ks", "w1"):
        assert same[key]["value"] == 0 and same[key]["low"] == 0 and same[key]["high"] == 0, key
    bigger = [particles(disc_labels(64, n=6, radius=1.2 * r, seed=s)) for s, r in enumerate((4.0, 5.0, 6.0, 5.5, 4.5))]
    stats = compare_sizes(bigger, true, n_boot=200, seed=1)
    median = stats["median_error"]
    assert 0.1 < median["value"] < 0.3 and median["low"] <= median["value"] <= median["high"]
    assert median["high"] - median["low"] > 0  # images differ, so resampling them moves the median


def test_evaluate_writes_particle_statistics_and_the_classical_baseline_finds_the_discs(tmp_path):
    from drgan.evaluate import EvaluateSettings, evaluate

    ids = ["a", "b", "c"]
    labels = {i: disc_labels(48, n=4, radius=5.0, seed=k) for k, i in enumerate(ids)}
    data = make_real(
        tmp_path / "real",
        {i: disc_image(labels[i], seed=k) for k, i in enumerate(ids)},
        {i: (labels[i] > 0) * 255 for i in ids},
        {"train": [], "test": ids},
    )
    from drgan.segmenters.predictors import load_predictor

    class Truth:  # a predictor that returns each image's own mask
        source, how = "masks", ""

        def check(self, items):
            pass

        def __call__(self, item):
            return (labels[item.id] > 0).astype(np.uint8)

    cfg = eval_cfg(data, tmp_path / "out", ["bootstrap=50"])
    result = evaluate(
        EvaluateSettings.from_config(cfg, need_models=False),
        predictors={"masks": Truth(), "classical": load_predictor("classical")},
    )
    exact = result["statistics"]["masks"]
    assert exact["median_error"]["value"] == 0 and exact["count_error"]["value"] == 0 and exact["ks"]["value"] == 0
    classical = result["statistics"]["classical"]
    assert abs(classical["count_error"]["value"]) < 0.2 and abs(classical["median_error"]["value"]) < 0.2
    text = (tmp_path / "out" / "statistics.md").read_text()
    assert "| masks | " in text and "| classical | " in text and "bootstrap" in text
    assert (tmp_path / "out" / "sizes.png").stat().st_size > 1000
    assert "median_error" in (tmp_path / "out" / "statistics.csv").read_text()
    # where particles are lost: the masks themselves lose none
    sources = exact["sources"]
    from skimage.measure import label

    n_true = sum(particles(label(labels[i] > 0, connectivity=1)).count for i in ids)  # touching discs are one
    assert sources["matched"] == sources["n_true"] == n_true
    assert sources["false"] == 0 and sources["diameter_offset"] == 0
    assert (
        "## Where particles are lost" in text and "sources/merged" in (tmp_path / "out" / "statistics.csv").read_text()
    )


def test_evaluate_leaves_specks_out_of_the_statistics_on_both_sides(tmp_path):
    from drgan.core.errors import ConfigError
    from drgan.evaluate import EvaluateSettings, evaluate

    ids = ["a", "b"]
    labels = {i: disc_labels(48, n=3, radius=6.0, seed=k) for k, i in enumerate(ids)}
    masks = {i: (labels[i] > 0) * 255 for i in ids}
    masks["a"][2, 40] = masks["a"][45, 2] = masks["a"][44, 44] = 255  # three 1-px specks in one annotation
    data = make_real(
        tmp_path / "real",
        {i: disc_image(labels[i], seed=k) for k, i in enumerate(ids)},
        masks,
        {"train": [], "test": ids},
    )

    class Clean:  # finds every particle and no speck
        source, how = "clean", ""

        def check(self, items):
            pass

        def __call__(self, item):
            return (labels[item.id] > 0).astype(np.uint8)

    def count_error(min_area):
        cfg = eval_cfg(data, tmp_path / f"out{min_area}", ["bootstrap=0", f"min_area_px={min_area}"])
        return evaluate(EvaluateSettings.from_config(cfg, need_models=False), predictors={"clean": Clean()})[
            "statistics"
        ]["clean"]["count_error"]["value"]

    assert count_error(8) == 0
    assert count_error(0) < 0  # the specks count as particles the prediction missed

    class Never(Clean):
        def __call__(self, item):
            raise AssertionError("predicted before the settings were checked")

    with pytest.raises(ConfigError, match="min_area_px"):
        evaluate(
            EvaluateSettings.from_config(eval_cfg(data, tmp_path / "bad", ["min_area_px=-1"]), need_models=False),
            predictors={"never": Never()},
        )


def test_error_sources_name_what_became_of_each_true_particle():
    from drgan.metrics.instance_scores import error_sources

    true = squares(40, [(2, 2, 6, 6), (2, 9, 6, 6), (12, 2, 6, 6), (12, 20, 6, 6), (2, 30, 8, 8), (25, 25, 10, 10)])
    pred = squares(40, [(2, 2, 6, 13), (12, 2, 6, 3), (12, 5, 6, 3), (12, 20, 6, 6), (15, 30, 4, 3), (24, 24, 12, 12)])
    # 1 + 2 merged into one prediction; 3 split in two halves; 4 exact; 5 missed (a false particle beside it);
    # 6 outlined 1 px too wide all round (IoU 100 / 144 > 0.5: matched, diameter offset +)
    found = error_sources(pred, true)
    assert (found["n_true"], found["n_pred"]) == (6, 6)
    assert {k: found[k] for k in ("matched", "merged", "split", "missed", "outline", "false")} == {
        "matched": 2,
        "merged": 2,
        "split": 1,
        "missed": 1,
        "outline": 0,
        "false": 1,
    }
    expected = [0.0, 2 * np.sqrt(144 / np.pi) - 2 * np.sqrt(100 / np.pi)]
    np.testing.assert_allclose(np.sort(found["diameter_offset"]), expected)
    # a prediction 3 x the particle's area holds all of it, IoU 1/3: badly outlined, not merged or missed
    wide = error_sources(squares(20, [(2, 2, 9, 9)]), squares(20, [(5, 5, 3, 9)]))
    assert (wide["outline"], wide["matched"], wide["false"]) == (1, 0, 0)


def test_the_area_weighted_median_is_the_large_particles_size_among_specks():
    from drgan.metrics.statistics import area_median, diameters_of, median_diameter

    # areas 1, 1, 1, 100 (x pi / 4): the three specks hold 3 of 103, so half the area lies in the 10-px particle
    assert area_median(np.array([1.0, 1.0, 10.0, 1.0])) == 10.0
    # equal halves: the smallest diameter whose cumulative share reaches one half
    assert area_median(np.array([3.0, 4.0, 5.0])) == 4.0  # shares 9 / 50, 25 / 50: 4 reaches 0.5 exactly
    assert np.isnan(area_median(np.zeros(0)))
    labels = np.zeros((40, 40), np.int32)
    labels[2:4, 2:4], labels[2:4, 30:32], labels[10:30, 10:30] = 1, 2, 3  # two 2 x 2 specks, one 20 x 20 square
    assert median_diameter([labels]) == pytest.approx(2 * np.sqrt(4 / np.pi))
    assert area_median(diameters_of([labels])) == pytest.approx(2 * np.sqrt(400 / np.pi))


def test_majority_holders_names_the_prediction_holding_more_than_half_of_each_true_particle():
    from drgan.metrics.instance_scores import majority_holders

    true = np.zeros((4, 8), np.int64)
    true[:, :4], true[:, 4:] = 1, 2
    pred = np.zeros_like(true)
    pred[:, :5] = 7  # all of particle 1, a quarter of particle 2
    pred[:, 5:7] = 9  # half of particle 2: not more than half
    assert majority_holders(pred, true) == {1: 7}
    pred[:, 5:] = 9  # three quarters of particle 2
    assert majority_holders(pred, true) == {1: 7, 2: 9}
