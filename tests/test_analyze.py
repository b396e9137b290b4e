"""drgan.analyze as the report a paper needs: the same particles and diameters as drgan.evaluate, cut particles counted
but not sized, the pixel size read from a TIFF, bootstrap intervals, the fitted distribution, overlays."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import tifffile
from conftest import compose
from test_segment import disc_image, make_real

from drgan.core.errors import ConfigError, DataError


def field(seed: int, size: int = 64) -> np.ndarray:
    """Discs of several radii, one of them cut by the left border, and a 2 px speck."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    labels = np.zeros((size, size), np.int32)
    for k in range(6):
        r = rng.uniform(3.0, 7.0)
        cy, cx = rng.uniform(r + 2, size - r - 2, 2)
        labels[((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r) & (labels == 0)] = k + 1
    labels[((yy - 30) ** 2 + xx**2 <= 25) & (labels == 0)] = 7  # cut by the left border
    labels[60:61, 60:62] = 8  # a speck of 2 px^2
    return labels


def class_map_of(labels: np.ndarray) -> np.ndarray:
    from drgan.segmenters.inference import separate_regions

    return separate_regions(labels)


def test_analyze_counts_and_sizes_the_particles_evaluate_does(tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.evaluate import EvaluateSettings, evaluate

    fields = {f"f{i}": field(i) for i in range(4)}
    real = make_real(tmp_path / "real", {k: disc_image(v) for k, v in fields.items()},
                     {k: (v > 0) * 255 for k, v in fields.items()}, {"train": [], "test": sorted(fields)})  # fmt: skip

    class TrueInstances:  # the true instances of each image, separated as a segmenter's split separates them
        source, how = "truth", ""

        def check(self, items):
            pass

        def __call__(self, item):
            return class_map_of(fields[item.id])

    result = evaluate(EvaluateSettings.from_config(compose([f"data={real}", f"out={tmp_path / 'eval'}", "bootstrap=0"], config_name="evaluate"), need_models=False),
                      predictors={"run0": TrueInstances()})  # fmt: skip
    cfg = compose([f"images={real / 'images'}", f"out={tmp_path / 'an'}", "bootstrap=200"], config_name="analyze")
    rows = analyze(AnalyzeSettings.from_config(cfg), predictor=TrueInstances())
    stats = result["statistics"]["run0"]
    summary = json.loads((tmp_path / "an" / "summary.json").read_text())["statistics"]
    assert summary["count"]["value"] == stats["count"]["value"] == len(rows)  # cut particles counted, specks not
    sized = sorted(r["equivalent_diameter_px"] for r in rows if r["sized"])
    assert summary["median_diameter"]["value"] == pytest.approx(stats["median_diameter"]["value"])
    assert summary["median_diameter"]["value"] == pytest.approx(np.median(sized))
    assert summary["mean_diameter"]["value"] == pytest.approx(stats["mean_diameter"]["value"])
    # the border-cut discs are rows (counted) but not sized; the 2 px specks are neither
    cut = [r for r in rows if r["touches_border"]]
    assert len(cut) == 4 and not any(r["sized"] for r in cut) and min(r["area_px"] for r in rows) >= 8
    assert summary["count_per_image"]["value"] == pytest.approx(len(rows) / 4)
    low, high = summary["median_diameter"]["low"], summary["median_diameter"]["high"]
    assert low <= summary["median_diameter"]["value"] <= high and low < high
    assert summary["model"]["chosen"] in ("normal", "lognormal", "bimodal")
    for name in ("statistics.md", "sizes.png", "histograms.png", "overlays/f0.png", "particles.csv"):
        assert (tmp_path / "an" / name).is_file()
    text = (tmp_path / "an" / "statistics.md").read_text()
    assert "| median diameter (px) |" in text and "unknown: no pixel size" in text


def test_the_pixel_size_comes_from_the_tiff_and_a_given_one_wins(tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze

    folder = tmp_path / "images"
    folder.mkdir()
    labels = field(0)
    for name in ("a", "b"):  # 1e6 px per cm: 10 nm per px
        tifffile.imwrite(folder / f"{name}.tif", (disc_image(labels) * 255).astype(np.uint8), resolution=(1e6, 1e6),
                         resolutionunit="CENTIMETER")  # fmt: skip
    cfg = compose([f"images={folder}", f"out={tmp_path / 'an'}", "bootstrap=0"], config_name="analyze")
    rows = analyze(AnalyzeSettings.from_config(cfg), predictor=lambda image: class_map_of(labels))
    assert rows[0]["equivalent_diameter_nm"] == pytest.approx(10 * rows[0]["equivalent_diameter_px"])
    summary = json.loads((tmp_path / "an" / "summary.json").read_text())
    assert summary["unit"] == "nm" and "10 nm/px from the images' metadata" in summary["pixel_size"]
    # count per µm²: each image is 64 x 64 px of 10 nm = 0.4096 µm²
    assert summary["statistics"]["count_per_area"]["value"] == pytest.approx(len(rows) / (2 * 0.4096))
    given = compose([f"images={folder}", f"out={tmp_path / 'an2'}", "bootstrap=0", "nm_per_px=2.5"],
                    config_name="analyze")  # fmt: skip
    rows = analyze(AnalyzeSettings.from_config(given), predictor=lambda image: class_map_of(labels))
    assert rows[0]["equivalent_diameter_nm"] == pytest.approx(2.5 * rows[0]["equivalent_diameter_px"])
    table = list(csv.DictReader((tmp_path / "an2" / "particles.csv").open()))
    assert {"equivalent_diameter_nm", "sized", "axis_ratio"} <= set(table[0])
    # read back per image as the reported sizes and the study summary read it: the rows of each image, in order
    from drgan.metrics.statistics import read_particle_table
    from drgan.pipeline.batch import sized_diameters

    back = read_particle_table(tmp_path / "an2" / "particles.csv", "equivalent_diameter_nm")
    assert sorted(back) == ["a", "b"]
    for image_id, read in back.items():
        mine = [r for r in table if r["image"] == image_id]
        np.testing.assert_allclose(read.diameter, [float(r["equivalent_diameter_nm"]) for r in mine])
        assert read.border.tolist() == [r["touches_border"] == "True" for r in mine] and read.border.any()
    whole = sized_diameters(tmp_path / "an2" / "particles.csv", "nm")
    np.testing.assert_allclose(np.sort(whole), np.sort([float(r["equivalent_diameter_nm"]) for r in table
                                                        if r["sized"] == "True"]))  # fmt: skip
    with pytest.raises(DataError, match="equivalent_diameter_um"):
        read_particle_table(tmp_path / "an2" / "particles.csv", "equivalent_diameter_um")
    assert read_particle_table(tmp_path / "missing.csv") == {}


def test_a_table_without_particles_has_every_column_and_reads_empty(tmp_path):
    """An analyze run that found nothing writes the header a run with particles writes (evaluate's reported sizes
    read it back: a header without axis_ratio stopped the tiny pipeline's evaluate)."""
    from drgan.analyze import EMPTY_TABLE_COLUMNS, _csv, particle_rows
    from drgan.metrics.statistics import read_particle_table

    labels = field(0)
    assert tuple(particle_rows("a", labels)[0]) == EMPTY_TABLE_COLUMNS  # the px columns of a row, in order
    (tmp_path / "none.csv").write_text(_csv([]))
    assert (tmp_path / "none.csv").read_text().strip().split(",") == list(EMPTY_TABLE_COLUMNS)
    assert read_particle_table(tmp_path / "none.csv") == {}
    (tmp_path / "old.csv").write_text("id,image,area_px,equivalent_diameter_px,touches_border,sized\n")
    assert read_particle_table(tmp_path / "old.csv") == {}  # an older run's empty table: nothing to read


@pytest.mark.parametrize("key, value", [("nm_per_px", "-1"), ("min_area_px", "-3"), ("bootstrap", "1.5")])
def test_bad_settings_stop_before_any_image_is_read(key, value, tmp_path):
    from drgan.analyze import AnalyzeSettings, analyze

    with pytest.raises(ConfigError, match=key):
        analyze(AnalyzeSettings.from_config(compose([f"images={tmp_path / 'none'}", f"{key}={value}"], config_name="analyze")),
                predictor=lambda image: image > 0.5)  # fmt: skip


@pytest.mark.parametrize("value", ["-1", "0", "true", "abc"])
def test_a_bad_pixel_size_stops_evaluate_before_any_checkpoint_is_read(value, tmp_path):
    from drgan.evaluate import EvaluateSettings

    real = make_real(tmp_path / "real", {"a": disc_image(np.zeros((8, 8)))}, {"a": np.zeros((8, 8), np.uint8)},
                     {"train": [], "val": [], "test": ["a"]})  # fmt: skip
    cfg = compose([f"data={real}", f"model={tmp_path / 'missing.ckpt'}", f"nm_per_px={value}"], config_name="evaluate")
    with pytest.raises(ConfigError, match="evaluate: nm_per_px="):
        EvaluateSettings.from_config(cfg)


def test_analyze_and_evaluate_yaml_and_their_settings_dataclasses_hold_the_same_defaults(tmp_path):
    """analyze.yaml / evaluate.yaml are the user's reference, AnalyzeSettings / EvaluateSettings the typed objects
    the stages read: every default agrees (the folders given aside), so no key has two values that can drift (as
    evaluate's min_area_px once did: 8 px^2 in the YAML, 0 in the code)."""
    import dataclasses

    from drgan.analyze import AnalyzeSettings
    from drgan.evaluate import EvaluateSettings

    # the folders are given; the inference block is the YAML's (its keys are checked by make_predictor, "auto"
    # resolved from the checkpoint: drgan.segmenters.calibrate)
    given = {"images", "out", "data", "models", "inference"}
    settings = AnalyzeSettings.from_config(compose(["images=I", "out=O"], config_name="analyze"))
    real = make_real(tmp_path / "real", {"a": disc_image(np.zeros((8, 8)))}, {"a": np.zeros((8, 8), np.uint8)},
                     {"train": [], "test": ["a"]})  # fmt: skip
    evaluated = EvaluateSettings.from_config(compose([f"data={real}", "model=M", "out=O"], config_name="evaluate"))
    for typed in (settings, evaluated):
        for f in dataclasses.fields(typed):
            if f.name in given:
                continue
            default = f.default_factory() if f.default is dataclasses.MISSING else f.default
            assert getattr(typed, f.name) == default, (type(typed).__name__, f.name)
    assert evaluated.models == ("M",) and settings.images.name == "I"
    assert settings.inference == evaluated.inference and settings.inference["split_core"] == "auto"
    with pytest.raises(ConfigError, match="min_area_px"):
        EvaluateSettings.from_config(compose([f"data={real}", "model=M", "min_area_px=-1"], config_name="evaluate"))
    with pytest.raises(ConfigError, match="bins"):
        AnalyzeSettings.from_config(compose(["images=I", "bins=0"], config_name="analyze"))
