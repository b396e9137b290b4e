"""drgan.profile: estimates from unannotated images, on synthetic discs of known sizes, grey, noise and grain."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import compose
from PIL import Image
from scipy import ndimage as ndi

from drgan.core.errors import ConfigError, DataError
from drgan.data import measurements as est
from drgan.data.classical import SegmentParams, resolve_params
from drgan.data.patches import window_starts

GREY = {"bright": 0.25, "dark": 0.75}  # background grey level
CONTRAST = {"bright": 0.4, "dark": -0.4}


def synthetic(polarity, rng, size=320, n=30, median=20.0, sigma=0.25, noise=0.03, grain=1.0, diameters=None):
    """Non-overlapping discs (diameters lognormal unless given) on a noisy background; returns (image, diameters)."""
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), GREY[polarity])
    drawn, centres = [], []
    wanted = diameters if diameters is not None else np.exp(rng.normal(np.log(median), sigma, n))
    for d in wanted:
        r = d / 2
        for _ in range(200):
            c = rng.uniform(r + 2, size - r - 2, 2)
            if all(np.hypot(*(c - c2)) > r + r2 + 3 for c2, r2 in centres):
                centres.append((c, r))
                image[(yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r] += CONTRAST[polarity]
                drawn.append(d)
                break
    white = rng.standard_normal((size, size))
    field = ndi.gaussian_filter(white, grain, mode="wrap") if grain > 0 else white
    image += noise * field / field.std()
    return np.clip(image, 0, 1).astype(np.float32), np.asarray(drawn)


def measure(images, polarity, scale=None):
    """Segment ``images`` as the profile does: the scale searched (or ``scale`` px where given, and only the neck
    depth chosen at it)."""
    given = None if scale is None else SegmentParams(scale=scale)
    params, _ = resolve_params(images, given, polarity)
    tables, fgs = [], []
    for image in images:
        labels, fg = est.segment_image(image, params, polarity)[:2]
        tables.append(est.particle_table(labels))
        fgs.append(fg)
    d = np.concatenate([t["diameter_px"][~t["touches_border"]] for t in tables])
    return d, est.background_noise(images, fgs)


@pytest.mark.parametrize("polarity", ["bright", "dark"])
def test_estimates_recover_polarity_background_noise_grain_and_median_diameter(polarity):
    from drgan.data.polarity import detect_polarity

    rng = np.random.default_rng(1)
    pairs = [synthetic(polarity, rng) for _ in range(3)]
    images, truth = [p[0] for p in pairs], np.concatenate([p[1] for p in pairs])
    assert detect_polarity(images).polarity == polarity
    d, noise = measure(images, polarity)
    assert abs(np.median(d) / np.median(truth) - 1) < 0.04
    assert abs(noise.background_grey - GREY[polarity]) < 0.005
    assert abs(noise.noise_sigma / 0.03 - 1) < 0.1
    assert abs(noise.grain_px - 1.0) < 0.2


def test_white_noise_reads_as_no_grain():
    rng = np.random.default_rng(2)
    image, _ = synthetic("bright", rng, grain=0.0, noise=0.02)
    _, noise = measure([image], "bright")
    assert noise.grain_px < 0.35 and abs(noise.noise_sigma / 0.02 - 1) < 0.1


def test_the_fit_picks_lognormal_for_lognormal_data_and_bimodal_for_two_sizes():
    rng = np.random.default_rng(3)
    fits, chosen = est.fit_sizes(np.exp(rng.normal(np.log(25), 0.3, 400)))
    assert chosen.kind == "lognormal" and {f.kind for f in fits} == {"normal", "lognormal", "bimodal"}
    assert abs(chosen.params["median"] / 25 - 1) < 0.05 and abs(chosen.params["sigma"] / 0.3 - 1) < 0.1
    two = np.concatenate([np.exp(rng.normal(np.log(12), 0.1, 200)), np.exp(rng.normal(np.log(36), 0.1, 200))])
    _, chosen = est.fit_sizes(two)
    assert chosen.kind == "bimodal"
    assert abs(chosen.params["median1"] / 12 - 1) < 0.05 and abs(chosen.params["median2"] / 36 - 1) < 0.05
    # On the images: discs of two sizes are segmented and fitted as a mixture too (at a scale between them: the
    # search is tested in test_particles.py and below)
    images = [synthetic("bright", rng, diameters=rng.permutation([12.0] * 25 + [32.0] * 12))[0] for _ in range(3)]
    d, _ = measure(images, "bright", scale=20.0)
    assert est.fit_sizes(d)[1].kind == "bimodal"


def test_particles_per_patch_count_centroids_inside_windows():
    assert list(window_starts(712, 256, 128)) == [36, 164, 292, 420]
    counts = est.patch_counts(np.array([10.0, 300.0, 300.0]), np.array([10.0, 10.0, 200.0]), (512, 512), 256)
    assert counts.reshape(3, 3).tolist() == [[1, 0, 0], [2, 1, 0], [2, 1, 0]]


def test_agglomeration_and_shape_suggestions():
    labels = np.zeros((40, 40), np.int32)
    labels[2:8, 2:8], labels[8:14, 2:8], labels[30:33, 10:34] = 1, 2, 3
    table = est.particle_table(labels)
    assert table["touches_other"].tolist() == [True, True, False]
    assert est.mesh_kind(float(table["axis_ratio"][2])) == "rod" and est.mesh_kind(1.0) == "sphere"
    grid = np.mgrid[5:100:10, 5:100:10].reshape(2, -1)
    assert est.clark_evans(grid[0], grid[1], 100 * 100) > 1.5  # a lattice is regular
    assert est.placement_kind(0.5, 1.0) == "poisson" and est.placement_kind(0.05, 1.1) == "random_2d"


def test_clustered_particles_seen_in_transmission_get_flat_piles():
    """A piled particle hides its contact in transmission (experiments/statistics/README.md): clustered particles of a
    transmission material get the flat poisson group, in every composed config; other materials keep the measured."""
    from drgan.profiling.proposal import placement_group

    assert placement_group("tio2_tsem", "poisson") == "poisson_flat"
    assert placement_group("tio2_tsem", "random_2d") == "random_2d"
    assert placement_group("tio2_sem", "poisson") == "poisson"
    flat = compose(["material=tio2_tsem"], config_name="train").placement
    piles = compose(["material=tio2_sem"], config_name="train").placement
    assert flat.max_clusters == 2 and flat.min_distance_factor == 0.85 and piles.max_clusters == 5
    assert flat.max_height == pytest.approx(0.45 * 30) and piles.max_height > 2 * flat.max_height


def test_pixel_size_from_tiff_resolution(tmp_path):
    import tifffile

    path = tmp_path / "a.tif"
    tifffile.imwrite(path, np.zeros((8, 8), np.uint8), resolution=(1e6, 1e6), resolutionunit="CENTIMETER")
    size, source = est.pixel_size_nm(path)
    assert size == pytest.approx(10.0) and "Resolution" in source
    tifffile.imwrite(path, np.zeros((8, 8), np.uint8))
    assert est.pixel_size_nm(path)[0] is None


def _folder(tmp_path, polarity, n=3):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(4)
    for i in range(n):
        image, _ = synthetic(polarity, rng)
        bar = np.full((16, image.shape[1]), 1.0, np.float32)  # an info bar to crop
        Image.fromarray((np.concatenate([image, bar]) * 255).round().astype(np.uint8)).save(folder / f"im{i}.png")
    return folder


def test_a_folder_whose_images_disagree_on_polarity_names_the_odd_ones(tmp_path, monkeypatch, caplog):
    from drgan.profile import ProfileSettings, profile

    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(4)
    for name, polarity in (("a", "bright"), ("b", "bright"), ("c", "dark")):
        image, _ = synthetic(polarity, rng)
        Image.fromarray((image * 255).round().astype(np.uint8)).save(folder / f"{name}.png")
    monkeypatch.chdir(tmp_path)
    overrides = [f"data.dir={folder}", "data.crop_rows=null", "name=mixed", f"out={tmp_path / 'out'}"]
    with caplog.at_level("WARNING", logger="drgan.profile"):
        result = profile(ProfileSettings.from_config(compose(overrides, config_name="profile")))
    assert result.polarity.value == "bright"
    warned = [r.getMessage() for r in caplog.records if "look like dark particles" in r.getMessage()]
    assert len(warned) == 1 and "c.png" in warned[0] and "a.png" not in warned[0]


@pytest.mark.parametrize("grow", [0, 2])
def test_sizes_are_measured_at_half_contrast_whatever_the_segmented_outline(tmp_path, monkeypatch, grow):
    """Outlines drawn ``grow`` px outside the particles (as grown outlines or a wide threshold do): the profile's
    sizes, which the material's size distribution takes, stay those of the particles at half contrast."""
    from skimage.segmentation import expand_labels

    from drgan.profile import ProfileSettings, profile

    folder = tmp_path / "images"
    folder.mkdir()
    rng, truth = np.random.default_rng(4), []
    for i in range(3):
        image, drawn = synthetic("bright", rng, median=24.0, sigma=0.15, noise=0.02)
        truth += list(drawn)
        image = ndi.gaussian_filter(image, 1.0)
        Image.fromarray((image * 255).round().astype(np.uint8)).save(folder / f"im{i}.png")
    segment = est.segment_image

    def wide(image, params, polarity):
        labels, foreground, *rest = segment(image, params, polarity)
        labels = expand_labels(labels, grow)
        return (labels, labels > 0, *rest)

    monkeypatch.setattr(est, "segment_image", wide)
    monkeypatch.chdir(tmp_path)
    overrides = [f"data.dir={folder}", "data.crop_rows=null", "name=blurred", f"out={tmp_path / 'out'}"]
    sizes = profile(ProfileSettings.from_config(compose(overrides, config_name="profile"))).sizes
    median = float(np.median(truth))
    assert sizes.segmented_median_diameter_px > median + 2 * grow - 1  # the outlines measured are that wide
    assert abs(sizes.outline_shift_px + grow) < 0.6  # half contrast found inside them by about what they grew
    assert abs(sizes.median_diameter_px / median - 1) < 0.03
    assert sizes.median_diameter_px == pytest.approx(
        sizes.segmented_median_diameter_px + 2 * sizes.outline_shift_px, abs=0.01
    )


def test_cli_end_to_end_writes_profile_figures_and_a_material_train_composes(tmp_path, monkeypatch):
    from drgan.profile import ProfileSettings, profile

    folder = _folder(tmp_path, "bright")
    monkeypatch.chdir(tmp_path)
    overrides = [f"data.dir={folder}", "data.crop_rows=[320,336]", "name=my_discs", f"out={tmp_path / 'out'}"]
    result = profile(ProfileSettings.from_config(compose(overrides, config_name="profile")))
    assert result.polarity.value == "bright" and result.data.split is None
    figures = ("sizes.png", "scale_search.png", "particles.png", "background_noise.png", "edge_profile.png")
    for name in ("profile.json", "report.md", *figures):
        assert (tmp_path / "out" / name).stat().st_size > 0
    saved = json.loads((tmp_path / "out" / "profile.json").read_text())
    search = saved["segmentation"]["scale_estimate"]  # every scale segmented and every fixed point, for the figure
    fixed = [dict(zip(search["candidate_fields"], c)) for c in search["candidates"]]
    assert len(search["grid"]) >= 2 * 8 and fixed and search["neck_depth"] in (0.0, 0.2)
    assert any(abs(f["scale"] / search["refined_px"] - 1) < 0.1 and f["basin"] >= 3 for f in fixed)
    # Discs without a ring: the edge profile shows none, and a secondary-electron parent takes no fringe anyway.
    assert saved["edge"]["ring"]["kind"] == "none" and saved["material"]["fringe"] is None
    assert abs(saved["sizes"]["median_diameter_px"] / 20 - 1) < 0.1
    assert saved["shape"]["mesh_kind"] == "sphere" and saved["material"]["parent"] == "sio2_him"

    cfg = compose(["material=my_discs"], config_name="train")
    assert cfg.material.name == "my_discs" and cfg.material.meshes.kind == "sphere"
    from drgan.profiling.proposal import (
        EXTENT_PER_DIAMETER,  # a material's size is a largest extent, the fit's a diameter
    )

    median = saved["sizes"]["fits"][1]["params"]["median"]
    assert cfg.material.particle_size_px == pytest.approx(EXTENT_PER_DIAMETER * median, abs=0.1)
    from drgan.scene import layout

    size, placement = layout.size_from_config(cfg.size), layout.placement_from_config(cfg.placement)
    assert type(size) is layout._SIZE_KINDS[saved["sizes"]["chosen"]]
    assert type(placement) is layout._PLACEMENT_KINDS[saved["agglomeration"]["placement"]]
    assert cfg.data.dir == str(folder.resolve()) and list(cfg.data.crop_rows) == [320, 336]
    assert cfg.renderer.spp == 16  # inherited from the parent (HIM)
    # a lit stage: the stage by light sampling alone (the parent's own renders keep the general default)
    assert cfg.renderer.integrator == "direct_light"
    assert compose(["material=sio2_him"], config_name="train").renderer.integrator == "direct_light_mis"
    # sharp outlines (discs drawn without blur) render through a sharper filter than the HIM parent's 3 px
    from drgan.profiling.proposal import filter_for_blur

    assert saved["edge_blur_px"] < 1.0 and cfg.material.filter_stddev == filter_for_blur(saved["edge_blur_px"]) == 0.5
    # The background's noise bounds the learned noise of an SEM material too (the parent's 0.2 let a GAN on clean
    # images learn 30 x the real noise); the grain stays the path tracer's (no noise_grain_px written)
    from drgan.profiling.proposal import NOISE_LIMIT_FACTOR

    bound = max(0.01, NOISE_LIMIT_FACTOR * saved["background"]["noise_sigma"])
    assert cfg.material.noise_sigma.max == pytest.approx(bound, abs=1e-4) and bound < 0.2
    assert "noise_grain_px:" not in (tmp_path / "drgan_conf" / "material" / "my_discs.yaml").read_text()
    # The neck depth the profile chose (its segmentation's) travels, and the report says why
    chosen = saved["segmentation"]["params"]["neck_depth"]
    assert chosen in (0.0, 0.2) and cfg.data.segment.neck_depth == chosen
    report = (tmp_path / "out" / "report.md").read_text()
    # the particles' arrangement travels in the material, and the report says what contact_weight=auto makes of it
    from drgan.segmenters.contacts import resolve_contact_weight

    clark_evans = saved["agglomeration"]["clark_evans_median"]
    assert clark_evans is not None and cfg.material.clark_evans == pytest.approx(clark_evans, abs=1e-4)
    contact = resolve_contact_weight("auto", "bright", clark_evans)[1].removeprefix("auto: ")
    assert f"(`drgan.segment model.contact_weight=auto`) takes contact weight {contact}." in report
    assert f"| data.segment.neck_depth | {chosen} | chosen by the segment sizes" in report
    assert f"- `data.segment.neck_depth`: {chosen} (" in report and "chosen with the scale" in report
    grown = saved["segmentation"]["outlines_grown"]  # the report says what the outlines' growth did
    n = saved["data"]["images"]
    assert 0 <= grown["images"] <= n and "- `data.segment.grow_outlines`: true: " in report
    assert (f"on {grown['images']} of {n} images" if grown["images"] else f"on none of the {n} images") in report
    # A scale chosen below min_separability for its alike segments writes the lowered value, and says why
    from drgan.profiling.proposal import data_settings
    from drgan.profiling.result import ProfileResult

    assert not saved["segmentation"]["scale_estimate"]["alike"]
    assert "min_separability" not in saved["material"]["data"]["segment"]
    alike = copy.deepcopy(saved)
    alike["segmentation"]["scale_estimate"]["alike"] = True
    alike["segmentation"]["params"]["min_separability"] = 0.58
    data, notes = data_settings(ProfileResult.from_dict(alike))
    assert data["segment"]["min_separability"] == 0.58
    assert notes["data.segment.min_separability"].startswith("0.58 (default 0.66): the particles' scale separates")
    # A scale that smooths more than the particles' size asks (a plateau) says so, with the segments' size
    assert not saved["segmentation"]["scale_estimate"]["plateau"]
    plateau = copy.deepcopy(saved)
    plateau["segmentation"]["scale_estimate"]["plateau"] = True
    note = data_settings(ProfileResult.from_dict(plateau))[1]["data.segment.scale"]
    size = saved["sizes"]["median_diameter_px"]
    assert "no scale agreed with its segments' size" in note and f"one size ({size:.1f} px)" in note

    with pytest.raises(ConfigError, match="exists"):
        profile(
            ProfileSettings.from_config(compose(overrides, config_name="profile"))
        )  # no overwrite without overwrite=true


def test_dark_images_inherit_the_transmission_material_and_get_a_grain(tmp_path, monkeypatch):
    from drgan.profile import ProfileSettings, profile

    folder = _folder(tmp_path, "dark", n=2)
    monkeypatch.chdir(tmp_path)
    overrides = [f"data.dir={folder}", "name=dark_discs", f"out={tmp_path / 'out'}", "data.segment.neck_depth=0.2"]
    # the discs' median diameter given (the search is the bright test's, above): keys given travel, with their values
    overrides += ["data.segment.grow_outlines=false", "data.segment.scale=20"]
    result = profile(
        ProfileSettings.from_config(compose(overrides, config_name="profile"))
    )  # crop_rows auto: the white bar found and dropped
    assert result.polarity.value == "dark" and result.material.parent == "tio2_tsem"
    assert result.data.crop_rows == "auto" and abs(result.sizes.median_diameter_px / 20 - 1) < 0.1
    text = (tmp_path / "drgan_conf" / "material" / "dark_discs.yaml").read_text()
    assert "  - tio2_tsem\n" in text and "noise_grain_px:" in text
    cfg = compose(["material=dark_discs"], config_name="train")
    assert cfg.material.polarity == "dark" and cfg.data.polarity == "dark" and cfg.data.crop_rows == "auto"
    assert cfg.data.segment.neck_depth == 0.2 and "    neck_depth: 0.2\n" in text  # a key given travels
    assert cfg.data.segment.scale == 20
    assert cfg.data.segment.grow_outlines is False and result.segmentation.outlines_grown["images"] == 0
    # No ring at the discs' edges: the transmission material renders no fringe, and says why.
    assert result.edge["ring"]["kind"] == "none" and result.material.fringe is None
    assert cfg.material.imaging.fringe is None and "#   edge fringe: none" in text
    assert cfg.material.noise_grain_px == pytest.approx(result.background.grain_px, abs=0.01)
    from drgan.profiling.proposal import (
        NOISE_LIMIT_FACTOR,  # the background shows the detector noise: it bounds the learned one
    )

    measured = result.background.noise_sigma
    assert cfg.material.noise_sigma.max == pytest.approx(max(0.01, NOISE_LIMIT_FACTOR * measured), abs=1e-4)


def test_edge_blur_reads_the_gaussian_of_blurred_outlines_with_or_without_a_bright_rim():
    yy, xx = np.mgrid[:192, :192]
    image, fg = np.full((192, 192), 0.3), np.zeros((192, 192), bool)
    for c in [(48, 48), (48, 144), (144, 48), (144, 144)]:
        disc = (yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= 30**2
        image[disc], fg = 0.7, fg | disc
    rim = fg & ~ndi.binary_erosion(fg, iterations=3)
    rng = np.random.default_rng(0)
    found = {}
    for sigma in (1.5, 2.0, 3.0):
        for name, sharp in (("step", image), ("rim", image + 0.3 * rim)):  # the SEM edge effect: a bright rim
            blurred = ndi.gaussian_filter(sharp, sigma) + 0.01 * rng.standard_normal(image.shape)
            found[sigma, name] = est.edge_blur(blurred, fg)
    for sigma in (1.5, 2.0, 3.0):
        assert abs(found[sigma, "step"] / sigma - 1) < 0.15 and abs(found[sigma, "rim"] / sigma - 1) < 0.25
    assert found[1.5, "step"] < found[2.0, "step"] < found[3.0, "step"]
    assert est.edge_blur(image, np.zeros_like(fg)) is None  # no outline: nothing measured


def test_filter_for_blur_interpolates_the_render_table_and_holds_its_ends():
    from drgan.profiling.proposal import FILTER_FOR_BLUR, filter_for_blur

    assert filter_for_blur(None) is None and filter_for_blur(0.5) == 0.5 and filter_for_blur(5.0) == 3.0
    for blur, filt in FILTER_FOR_BLUR:
        assert filter_for_blur(blur) == filt
    assert filter_for_blur(2.24, 0.5) == 1.0  # 2.24 image px seen at half the px: 1.12 render px


def test_whole_particle_counts_count_boxes_off_every_window_edge():
    boxes = np.array([[10, 10, 20, 20], [0, 40, 10, 50], [30, 30, 70, 70]])  # inside; on the top edge; straddling
    counts = est.whole_particle_counts(boxes, (64, 64), 64, 32)
    assert counts.tolist() == [1]  # one 64 px window: only the first box is whole
    counts = est.whole_particle_counts(boxes, (100, 100), 64, 32)  # windows at 2 and 34 (a centred grid)
    assert counts.shape == (4,) and counts.max() <= 2 and est.whole_particle_counts(boxes, (50, 50), 64).size == 0


def test_view_window_widens_for_large_particles_within_the_images():
    assert est.view_window(30.0, 256, 1024) == 256  # TiO2: the render size
    assert est.view_window(131.0, 256, 1024) == 256  # EMPS actbio's rings fit (0.51 of the window)
    assert est.view_window(310.0, 256, 1024) == 1024 and est.view_window(310.0, 256, 512) == 512  # capped


def test_large_particles_get_a_training_window_wider_than_the_render(tmp_path, monkeypatch):
    """Particles that fill a render-sized window (EMPS saa890: 282 px in 256 px windows, none whole in any) are
    learned from wider windows, area-averaged to the render: the material says how wide, counts are per window,
    and the detector's grain is written in render px."""
    from drgan.profile import ProfileSettings, profile

    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(5)
    for i in range(3):
        image, _ = synthetic("dark", rng, size=160, n=4, median=40.0, sigma=0.1, grain=2.0)
        Image.fromarray((image * 255).round().astype(np.uint8)).save(folder / f"im{i}.png")
    monkeypatch.chdir(tmp_path)
    overrides = [f"data.dir={folder}", "name=big_discs", f"out={tmp_path / 'out'}", "patch_size=32",
                 "data.crop_rows=null", "data.segment.scale=40", "data.segment.neck_depth=0.0"]  # fmt: skip
    result = profile(ProfileSettings.from_config(compose(overrides, config_name="profile")))
    counts = result.particles_per_patch
    assert abs(result.sizes.median_diameter_px / 40 - 1) < 0.15
    assert counts.patch_size == 128 and counts.render_px == 32  # 44 px extent > 0.6 x 64; 256 > the 160 px images
    # one 128 px window per 160 px image: 3 windows, far from 16 with 3 whole particles, so training keeps windows
    # with one whole particle (as it counts them: bounding box off every window edge)
    assert counts.whole["windows"] == 3 and counts.whole["at_least_3"] <= counts.whole["at_least_1"] <= 3
    cfg = compose(["material=big_discs"], config_name="train")
    assert cfg.material.view_width == 128 and cfg.data.view_width == 128 and cfg.data.min_particles == 1
    # rendered at the profile's patch size, the real windows area-averaged to it (EMPS saa890 rendered 512 px windows
    # at 512 px, 4 x the pixels of every GAN step and generated pair, while the material said 256)
    assert cfg.renderer.resolution == 32 and cfg.data.patch_size == 32
    assert cfg.renderer.integrator == "direct_light_mis"  # transmission: no stage to light, nothing written
    assert cfg.material.noise_grain_px == pytest.approx(result.background.grain_px * 32 / 128, abs=0.01)
    # The scene's particle range is that of the windows training keeps (>= data.min_particles), not of the few with
    # 3 or more (EMPS saa890: 6-6 from those where its 512 px windows hold 1-2 particles)
    import dataclasses

    from drgan.profiling.proposal import material_settings

    fits, chosen = est.fit_sizes(np.asarray([38.0, 40.0, 41.0, 43.0, 39.0, 42.0]), seed=0)

    def n_range(at_least_3: int) -> tuple[int, int]:
        kept = {"1": {"windows": 30, "p10": 1.0, "p90": 2.0}, "2": {"windows": 12, "p10": 2.0, "p90": 3.0},
                "3": {"windows": 2, "p10": 6.0, "p90": 6.0}}  # fmt: skip
        whole = {**counts.whole, "at_least_3": at_least_3, "at_least_2": 0, "at_least_1": 30}
        patch = dataclasses.replace(counts, kept_counts=kept, with_3_or_more=kept["3"], whole=whole, windows=30)
        material = material_settings(dataclasses.replace(result, particles_per_patch=patch), fits, chosen)[2]
        return material["n_particles_min"], material["n_particles"]

    assert n_range(at_least_3=2) == (1, 2)  # min_particles 1: windows with >= 1
    assert n_range(at_least_3=40) == (6, 6)  # min_particles stays 3 (enough windows show 3 whole particles)
    # a bimodal fit: the size group's two components as normals of largest extents (a lognormal's mean and std)
    from drgan.profiling.proposal import EXTENT_PER_DIAMETER

    two = np.concatenate([np.full(30, 20.0), np.full(30, 60.0)]) * np.exp(np.random.default_rng(0).normal(0, 0.05, 60))
    fits2, bimodal = est.fit_sizes(two, seed=0)
    assert bimodal.kind == "bimodal"
    size, notes = material_settings(result, fits2, bimodal)[3:]
    q = bimodal.params
    mean1 = EXTENT_PER_DIAMETER * q["median1"] * np.exp(q["sigma1"] ** 2 / 2)
    assert size["mean1"] == pytest.approx(mean1, abs=1e-3) and size["weight1"] == pytest.approx(q["weight1"], abs=1e-3)
    assert "two lognormal components" in notes["size"]
    assert material_settings(result, fits, chosen)[3] == {}  # no size group for a single mode
    assert (
        "#   view_width: 128 real px per training window, rendered at 32 px"
        in (tmp_path / "drgan_conf" / "material" / "big_discs.yaml").read_text()
    )


def test_errors_before_compute(tmp_path, monkeypatch):
    from drgan.profile import ProfileSettings, profile

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="data.dir"):
        profile(ProfileSettings.from_config(compose(["name=x"], config_name="profile")))
    with pytest.raises(ConfigError, match="no such folder"):
        profile(
            ProfileSettings.from_config(compose([f"data.dir={tmp_path / 'missing'}", "name=x"], config_name="profile"))
        )
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no image files"):
        profile(
            ProfileSettings.from_config(compose([f"data.dir={tmp_path / 'empty'}", "name=x"], config_name="profile"))
        )
    folder = _folder(tmp_path, "bright", n=1)
    with pytest.raises(DataError, match="crop_rows"):
        profile(
            ProfileSettings.from_config(
                compose([f"data.dir={folder}", "data.crop_rows=[300,400]", "name=x"], config_name="profile")
            )
        )
    with pytest.raises(ConfigError, match="name"):
        profile(ProfileSettings.from_config(compose([f"data.dir={folder}"], config_name="profile")))
    with pytest.raises(ConfigError, match="name=tio2_tsem: a material drgan ships has that name"):
        profile(
            ProfileSettings.from_config(compose([f"data.dir={folder}", "name=tio2_tsem"], config_name="profile"))
        )  # would shadow the shipped one
    assert not (tmp_path / "drgan_conf").exists()


def test_a_bright_stage_beyond_the_parents_reach_widens_its_limit_enough():
    """The paper SEM/HIM materials render their stage at most ~0.15 grey; an SEM image with a mid-grey stage (EMPS cej:
    0.43) gets a stage limit under which a render reaches that grey. Dark (transmission) parents have no lit stage."""
    import torch

    from drgan.launch.configs import compose
    from drgan.models.gan_module import GANModule
    from drgan.profiling.proposal import parent_stage_reach, stage_limits

    limit, grey = parent_stage_reach("tio2_him")
    assert limit == 0.3 and 0.05 < grey < 0.3
    assert stage_limits("tio2_him", 0.5 * grey) is None and stage_limits("tio2_tsem", 0.8) is None
    widened, why = stage_limits("tio2_him", 0.43)
    assert limit < widened["max"] <= 5.0 and "0.430 grey" in why
    cfg = compose(["material=tio2_him", f"material.imaging.stage_bsdf.base_color.max={widened['max']}",
                   "renderer.spp=16", "renderer.resolution=64"], config_name="train")  # fmt: skip
    module = GANModule.from_config(cfg)
    learned = module.generator.learned
    values = torch.tensor([p.high if p.key == "stage.base_color" else 0.5 * (p.low + p.high) for p in learned])
    phi = torch.as_tensor(module.sample_phi(1, seed=0)[0], dtype=torch.float32)
    with torch.no_grad():
        image = module.generator.render_one(phi, values, seed=1)[0].numpy()
    assert image[module.generator.scene.instance_labels() == 0].mean() > 0.43


def test_profile_yaml_and_the_settings_dataclass_hold_the_same_defaults(tmp_path, monkeypatch):
    """profile.yaml is the user's reference, ProfileSettings the typed source the stage reads: their defaults agree
    (the interpolated out and the split, resolved to a file or None, aside), and a wrong value fails naming its key."""
    import dataclasses

    from drgan.profile import ProfileSettings

    monkeypatch.chdir(tmp_path)
    folder = _folder(tmp_path, "bright", n=1)
    settings = ProfileSettings.from_config(compose([f"data.dir={folder}", "name=x"], config_name="profile"))
    defaults = {f.name: f for f in dataclasses.fields(ProfileSettings)}
    for key in ("crop_rows", "polarity", "patch_size", "max_images", "overwrite", "conf_dir", "seed"):
        default = defaults[key].default
        assert getattr(settings, key) == default, key
    assert settings.segment == defaults["segment"].default_factory() == SegmentParams()
    assert settings.split is None  # no split.json beside the folder: every image
    assert settings.out == Path("runs/profile/x") and settings.conf_path == Path("drgan_conf/material/x.yaml")
    for override, key in (
        ("patch_size=8", "patch_size"),
        ("max_images=0", "max_images"),
        ("data.polarity=grey", "polarity"),
    ):
        with pytest.raises(ConfigError, match=key):
            ProfileSettings.from_config(compose([f"data.dir={folder}", "name=x", override], config_name="profile"))
