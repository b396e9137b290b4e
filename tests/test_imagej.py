"""Outlines for Fiji and napari (drgan.data.imagej): traced ROIs give back the particles' pixels, label TIFFs keep
ids and pixel size, and analyze writes both for the particles of its particles.csv."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from drgan.data.imagej import (
    fill_polygon,
    polygon_area,
    read_label_tiff,
    read_roi_set,
    traced_outline,
    write_label_tiff,
    write_roi_set,
)


def test_a_single_pixel_and_an_l_shape_are_outlined_by_their_pixel_corners():
    one = np.zeros((3, 3), bool)
    one[1, 1] = True
    assert traced_outline(one).tolist() == [[1, 1], [2, 1], [2, 2], [1, 2]]  # (x, y) corners, clockwise
    ell = np.zeros((4, 4), bool)
    ell[0:3, 0] = True
    ell[2, 1] = True
    points = traced_outline(ell)
    assert sorted(points.tolist()) == sorted([[0, 0], [1, 0], [1, 2], [2, 2], [2, 3], [0, 3]])
    assert polygon_area(points) == 4.0


def test_random_particles_round_trip_through_an_imagej_roi_set_exactly(tmp_path):
    from skimage.measure import label
    from skimage.morphology import disk

    rng = np.random.default_rng(3)
    labels = np.zeros((96, 128), np.int64)
    n = 0
    for _ in range(14):  # discs, ellipses and ragged blobs, some touching the border
        r, c = rng.integers(0, 96), rng.integers(0, 128)
        blob = np.zeros_like(labels, dtype=bool)
        size = int(rng.integers(2, 9))
        d = disk(size).astype(bool)
        d &= rng.random(d.shape) > 0.15  # ragged outlines
        r0, c0 = max(r - size, 0), max(c - size, 0)
        part = d[r0 - (r - size) : r0 - (r - size) + 96 - r0, c0 - (c - size) : c0 - (c - size) + 128 - c0]
        blob[r0 : r0 + part.shape[0], c0 : c0 + part.shape[1]] = part
        blob &= labels == 0
        for piece in range(1, label(blob, connectivity=1).max() + 1):  # drgan's particles: 4-connected, no holes
            from scipy import ndimage as ndi

            one = ndi.binary_fill_holes(label(blob, connectivity=1) == piece) & (labels == 0)
            if one.sum() >= 3:
                n += 1
                labels[one] = n
    written = write_roi_set(tmp_path / "rois.zip", labels)
    assert written == n >= 10
    back = read_roi_set(tmp_path / "rois.zip", labels.shape)
    assert sorted(back, key=int) == [str(i) for i in range(1, n + 1)]
    for name, mask in back.items():
        truth = labels == int(name)
        if ndi_components(truth) == 1:
            assert np.array_equal(mask, truth), name  # the same pixels, as ImageJ fills a traced ROI


def ndi_components(mask):
    from scipy import ndimage as ndi

    return ndi.label(mask)[1]


def test_label_tiffs_keep_ids_and_the_pixel_size_in_nm(tmp_path):
    labels = np.zeros((20, 30), np.int64)
    labels[2:6, 3:9], labels[10:15, 10:12] = 7, 300
    write_label_tiff(tmp_path / "a.tif", labels, nm_per_px=2.5)
    back, nm = read_label_tiff(tmp_path / "a.tif")
    assert back.dtype == np.uint16 and np.array_equal(back, labels) and nm == pytest.approx(2.5)
    write_label_tiff(tmp_path / "b.tif", labels, None)
    assert read_label_tiff(tmp_path / "b.tif")[1] is None
    import tifffile

    with tifffile.TiffFile(tmp_path / "a.tif") as tif:  # what Fiji reads: an ImageJ TIFF, unit nm
        assert tif.is_imagej and tif.imagej_metadata["unit"] == "nm"


def test_fill_polygon_reads_a_square_as_imagej_does():
    assert fill_polygon(np.array([[1, 1], [4, 1], [4, 3], [1, 3]]), (5, 6)).sum() == 6


def test_analyze_writes_a_label_tiff_and_roi_set_per_image_matching_its_particles_csv(tmp_path):
    from PIL import Image

    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.launch.configs import compose

    images = tmp_path / "images"
    images.mkdir()
    yy, xx = np.mgrid[:64, :64]
    truth = {}
    for k, centres in enumerate([[(16, 16, 6), (40, 44, 9), (60, 5, 4)], [(30, 30, 10)]]):
        img = np.full((64, 64), 0.2)
        for r, c, rad in centres:
            img[(yy - r) ** 2 + (xx - c) ** 2 <= rad * rad] = 0.8
        Image.fromarray((img * 255).astype(np.uint8)).save(images / f"im{k}.png")
        truth[f"im{k}"] = img

    def predictor(image):  # the particle class where the image is bright, a speck below min_area added
        classes = (np.asarray(image) > 0.5).astype(np.int64)
        classes[0, 63] = 1
        return classes

    cfg = compose([f"images={images}", f"out={tmp_path / 'out'}", "nm_per_px=3.0", "bootstrap=0", "min_area_px=5"],
                  config_name="analyze")  # fmt: skip
    rows = analyze(AnalyzeSettings.from_config(cfg), predictor=predictor)
    table = list(csv.DictReader(open(tmp_path / "out" / "particles.csv")))
    assert len(table) == len(rows) == 4
    for image in ("im0", "im1"):
        labels, nm = read_label_tiff(tmp_path / "out" / "labels" / f"{image}.tif")
        assert nm == pytest.approx(3.0)
        mine = {int(r["id"]): int(r["area_px"]) for r in table if r["image"] == image}
        assert sorted(np.unique(labels[labels > 0]).tolist()) == sorted(mine)  # the speck is not in it
        for i, area in mine.items():
            assert int((labels == i).sum()) == area
        rois = read_roi_set(tmp_path / "out" / "rois" / f"{image}.zip", labels.shape)
        assert {int(k) for k in rois} == set(mine)
        for name, mask in rois.items():
            assert abs(int(mask.sum()) - mine[int(name)]) <= 0.01 * mine[int(name)]


def _chromium() -> str | None:
    import shutil

    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _analyzed(tmp_path):
    """An analyze folder of two images with real particles (a stub predictor: the bright pixels)."""
    from PIL import Image

    from drgan.analyze import AnalyzeSettings, analyze
    from drgan.launch.configs import compose

    images = tmp_path / "images"
    images.mkdir()
    yy, xx = np.mgrid[:96, :128]
    rng = np.random.default_rng(1)
    for k in range(2):
        img = np.full((96, 128), 0.2)
        for _ in range(6):
            r, c, rad = rng.integers(12, 84), rng.integers(12, 116), rng.integers(4, 10)
            img[(yy - r) ** 2 + (xx - c) ** 2 <= rad * rad] = 0.8
        Image.fromarray((img * 255).astype(np.uint8)).save(images / f"field{k}.png")
    cfg = compose([f"images={images}", f"out={tmp_path / 'out'}", "nm_per_px=2.0", "bootstrap=50"],
                  config_name="analyze")  # fmt: skip
    rows = analyze(AnalyzeSettings.from_config(cfg), predictor=lambda image: (np.asarray(image) > 0.5).astype(np.int64))
    return tmp_path / "out", rows


def test_the_statistics_page_is_one_file_with_its_figures_overlays_and_table_inside(tmp_path):
    out, rows = _analyzed(tmp_path)
    text = (out / "statistics.html").read_text()
    assert text.count('src="data:image/png;base64,') >= 2 and text.count('src="data:image/jpeg;base64,') == 2
    assert "<table>" in text and "median diameter" in text  # statistics.md rendered, its table a table
    assert 'src="http' not in text and "<link" not in text  # nothing to fetch
    assert f"{len(rows)} rows" in text and "drganTable" in text


@pytest.mark.skipif(_chromium() is None, reason="no Chromium here (.ci/run installs Debian's chromium)")
def test_the_statistics_page_renders_in_a_headless_browser_with_its_figures_and_sortable_table(tmp_path):
    import subprocess

    from PIL import Image

    out, rows = _analyzed(tmp_path)
    page = (out / "statistics.html").resolve().as_uri()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--hide-scrollbars"]
    dom = subprocess.run([_chromium(), *flags, "--dump-dom", page], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    body = dom.stdout.split('id="particles"', 1)[1]
    assert body.count("<tr>") == len(rows) + 1  # the table the script built: a header and one row per particle
    assert 'style="display: block;"' in dom.stdout.split('id="overlays"', 1)[1]  # the gallery shows its first image
    shot = tmp_path / "page.png"
    done = subprocess.run([_chromium(), *flags, f"--screenshot={shot}", "--window-size=1200,2400", page],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0 and shot.is_file(), done.stderr[-2000:]
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int16)
    colourful = (pixels.max(axis=2) - pixels.min(axis=2)) > 60  # the figures' coloured lines and bars
    assert colourful.mean() > 0.002, "the screenshot shows no figure"


def test_the_pipeline_report_page_embeds_the_figures_its_markdown_links_to(tmp_path):
    from drgan.pipeline.report import report_html

    out, rows = _analyzed(tmp_path)
    run = out.parent  # a pipeline folder: analyze/ inside it
    out.rename(run / "analyze")
    text = "# drgan pipeline `x`\n\n| stage | state |\n|---|---|\n| analyze | done |\n\nLook at: [sizes](analyze/sizes.png).\n"
    page = report_html(text, run, "drgan pipeline x")
    assert "<table>" in page and page.index("analyze/sizes.png</figcaption>") > page.index("Look at:")
    assert page.count("data:image/png;base64,") == 1 and page.count("data:image/jpeg;base64,") == 2
    assert f"{len(rows)} rows" in page


def test_the_napari_reader_opens_an_analyze_folder_as_images_and_labels_with_the_particle_table(tmp_path):
    from drgan.data.napari_reader import get_reader

    out, rows = _analyzed(tmp_path)
    assert get_reader(str(tmp_path / "images")) is None  # not a run: napari asks another plugin
    reader = get_reader(str(out))
    layers = reader(str(out))
    kinds = [(meta["name"], kind) for _, meta, kind in layers]
    assert kinds == [("field0", "image"), ("field0 particles", "labels"), ("field1", "image"),
                     ("field1 particles", "labels")]  # fmt: skip
    for data, meta, kind in layers:
        assert meta["scale"] == (2.0, 2.0)  # nm per px, from the label TIFF
        if kind == "labels":
            image = meta["name"].split()[0]
            mine = [r for r in rows if r["image"] == image]
            assert meta["features"]["index"] == [r["id"] for r in mine]
            assert meta["features"]["area_px"] == [int((data == r["id"]).sum()) for r in mine]
            assert set(np.unique(data[data > 0])) == {r["id"] for r in mine}
    run = tmp_path / "run"  # a pipeline run folder: its analyze/ inside
    run.mkdir()
    out.rename(run / "analyze")
    assert len(get_reader(str(run))(str(run))) == 4


def test_the_napari_manifest_is_valid_and_points_at_the_reader():
    npe2 = pytest.importorskip("npe2", reason="npe2 (the dev extra) validates napari manifests")
    from pathlib import Path

    import drgan.data.napari_reader as module

    manifest = npe2.PluginManifest.from_file(Path(module.__file__).parent.parent / "napari.yaml")
    (reader,) = manifest.contributions.readers
    (command,) = manifest.contributions.commands
    assert reader.command == command.id and reader.accepts_directories
    assert command.python_name == "drgan.data.napari_reader:get_reader"
    import importlib

    name, attribute = command.python_name.split(":")
    assert getattr(importlib.import_module(name), attribute) is module.get_reader


def test_drgan_view_says_what_is_missing(tmp_path, capsys):
    from drgan.view import main

    assert main([str(tmp_path)]) == 1 and "not a drgan run or analyze folder" in capsys.readouterr().err
    out, _ = _analyzed(tmp_path)
    try:
        import napari  # noqa: F401
    except ImportError:  # napari is an optional extra: without it, the message says how to get it
        assert main([str(out)]) == 1 and 'pip install "drgan[napari]"' in capsys.readouterr().err
