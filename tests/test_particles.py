"""drgan.data.classical: the scale-adaptive segmentation on small generated images (grain, scale bars and text,
touching particles, an empty field, 16-bit and RGB input)."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage as ndi

from drgan.core.errors import ConfigError, DataError
from drgan.data import annotations
from drgan.data import classical as P


def discs(size=192, diameter=24.0, n=12, polarity="bright", noise=0.02, grain=0.0, seed=0, gap=3.0):
    """(image in [0, 1], true diameters, centres): discs of one size on a flat background, Gaussian noise blurred
    by ``grain`` px; ``gap`` < 0 lets neighbours overlap (touching particles)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), 0.3 if polarity == "bright" else 0.7)
    r, centres = diameter / 2, []
    for _ in range(2000):
        if len(centres) == n:
            break
        c = rng.uniform(r + 2, size - r - 2, 2)
        if all(np.hypot(*(c - c2)) > 2 * r + gap for c2 in centres):
            centres.append(c)
            image[(yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= r * r] += 0.35 if polarity == "bright" else -0.35
    field = rng.standard_normal((size, size))
    field = ndi.gaussian_filter(field, grain) if grain else field
    image += noise * field / field.std()
    return np.clip(image, 0, 1).astype(np.float32), np.full(len(centres), 2 * np.sqrt(np.pi * r * r / np.pi)), centres


def measured(image, polarity):
    params, _ = P.resolve_params([image], None, polarity)
    labels, _ = P.segment_particles(image, params, polarity)
    return params, labels, P.segment_diameters(labels, params)


def test_grainy_dark_particles_are_found_at_their_size():
    image, truth, _ = discs(diameter=30, n=10, polarity="dark", noise=0.08, grain=2.0, seed=1)
    params, labels, d = measured(image, "dark")
    assert abs(np.median(d) / 30 - 1) < 0.1
    assert abs(params.scale / 30 - 1) < 0.15 and params.sigma > 1  # smoothing follows the size, not 1 px
    assert 8 <= len(np.unique(labels)) - 1 <= 12


def test_the_scale_search_shows_its_progress_only_when_asked(capsys):
    image, _, _ = discs(size=96, diameter=20, n=4, seed=2)
    quiet, _ = P.resolve_params([image], None, "bright")
    assert capsys.readouterr().err == ""
    shown, _ = P.resolve_params([image], None, "bright", progress=True)
    err = capsys.readouterr().err  # not a terminal here: drgan.core.progress's line when the search ends
    assert re.search(r"progress: particle scale search (\d+)/\1 scales \(100 %\), .* so far, done", err), err
    assert shown == quiet  # the bar changes nothing it measures


def test_scale_bar_and_text_are_not_particles():
    image, _, _ = discs(size=256, diameter=20, n=14, seed=2)
    canvas = Image.fromarray((image * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    pen.rectangle((150, 236, 240, 241), fill=255)  # a scale bar, bottom right
    pen.text((160, 214), "200 nm", fill=255, font=ImageFont.load_default(size=14))
    pen.text((4, 4), "(a)", fill=255, font=ImageFont.load_default(size=18))
    image = np.asarray(canvas, np.float32) / 255
    mask = annotations.annotation_mask(image)
    assert mask[236:242, 150:241].all() and mask[:24, :30].any() and mask[210:232, 158:215].any()
    params, labels, d = measured(image, "bright")
    assert not (labels > 0)[mask].any()  # nothing segmented on the bar, its text or the panel letter
    assert abs(np.median(d) / 20 - 1) < 0.1 and abs(params.scale / 20 - 1) < 0.15


def test_a_scale_bar_softened_by_resampling_is_found_and_a_rod_is_not():
    """A figure resampled (EMPS ec2cc16d2a: a white bar and label peaking at 0.92): they are no longer within
    ANNOTATION_LEVEL of white, but still drawn solid and straight within SOFT_LEVEL; a rod as pale near the same edge
    is not a solid strip of one width, and stays a particle."""
    yy, xx = np.mgrid[:256, :256]
    image = np.full((256, 256), 0.4)
    rod = ((yy - 226) / 5.0) ** 2 + ((xx - 60) / 40.0) ** 2 <= 1  # 80 x 10 px, horizontal, near the bottom
    image[rod] = 0.92
    canvas = Image.fromarray((image * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    pen.fontmode = "1"  # solid strokes, then softened with the rest
    pen.rectangle((150, 236, 240, 241), fill=235)  # a scale bar, bottom right
    pen.text((160, 214), "200 nm", fill=235, font=ImageFont.load_default(size=16))
    image = ndi.gaussian_filter(np.asarray(canvas, np.float32) / 255, 0.5)
    assert image.max() < 1 - annotations.ANNOTATION_LEVEL  # nothing is drawn in white
    mask = annotations.annotation_mask(image)
    assert mask[237:241, 152:239].all()  # the bar
    text = (image >= 1 - annotations.SOFT_LEVEL) & (yy < 232) & (xx >= 150)
    assert text.sum() > 30 and mask[text].mean() > 0.9  # its label
    assert not mask[rod].any()  # the rod
    params, labels, _ = measured(image, "bright")
    assert labels[rod].any() and not (labels > 0)[mask].any()  # the rod is a particle, the bar and label are not


def test_a_scale_bar_drawn_across_bright_particles_is_found_and_their_highlights_are_not():
    """A white bar drawn over bright spheres with saturated highlights (EMPS 226dc58f03): joined to the highlights
    above and below it, its group is no bar; the bar is found all the same and the highlights are left alone."""
    yy, xx = np.mgrid[:256, :256]
    image = np.full((256, 256), 0.35)
    for cx in (70, 130, 190):  # a row of spheres across the bottom, each with white highlights touching the bar
        image[np.hypot(yy - 226, xx - cx) <= 28] = 0.8
        for cy in (229, 246):
            image[np.hypot(yy - cy, xx - cx) <= 5] = 1.0
    image[234:241, 60:230] = 1.0  # the scale bar, across the spheres and their crests
    mask = annotations.annotation_mask(image)
    assert mask[234:241, 60:230].all()
    crests = (image == 1.0) & ((yy < 232) | (yy > 243)) & (yy > 150)
    assert crests.sum() > 50 and not mask[crests].any()


def test_a_mark_on_a_particle_leaves_it_whole():
    """A label printed on a particle is a mark (never thresholded), but the particle goes on under it: its segment
    is the whole disc, one piece; a label on the film stays out of every segment."""
    yy, xx = np.mgrid[:256, :256]
    image = np.full((256, 256), 0.3)
    for cy, cx in ((50, 128), (180, 70), (180, 190)):
        image[np.hypot(yy - cy, xx - cx) <= 44] = 0.65
    canvas = Image.fromarray((image * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    pen.text((116, 28), "(b)", fill=0, font=ImageFont.load_default(size=18))  # black, on the top disc, near the edge
    pen.text((116, 228), "(a)", fill=255, font=ImageFont.load_default(size=18))  # white, on the film
    image = np.asarray(canvas, np.float32) / 255
    marks = P.prepare(image, "bright", True).annotations
    disc = np.hypot(yy - 50, xx - 128) <= 44
    assert marks[disc].sum() > 20 and marks[yy > 200].sum() > 20  # both labels are read as marks
    params = P.SegmentParams(scale=88.0, neck_depth=0.0, grow_outlines=False).resolved()
    labels = P.segment_with_report(image, params, "bright").labels
    inside = np.unique(labels[np.hypot(yy - 50, xx - 128) <= 42])
    assert inside.size == 1 and inside[0] > 0  # one segment without pinholes: the whole disc
    assert not (labels > 0)[marks & (yy > 200)].any()  # the label on the film is no particle


def figure_crop(polarity: str) -> tuple[np.ndarray, float]:
    """A figure as users crop it from a paper: particles, a label box "d" with a grey frame top left, and the
    microscope's data bar along the bottom (near-white, framed, with text), saved as JPEG (grey ringing at every
    edge, no pixel exactly white)."""
    import io

    image, _, _ = discs(size=320, diameter=28, n=14, polarity=polarity, seed=4)
    canvas = Image.fromarray((image * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    pen.rectangle((6, 6, 52, 52), fill=170)  # the label box's frame
    pen.rectangle((12, 12, 46, 46), fill=250)
    pen.text((20, 14), "d", fill=0, font=ImageFont.load_default(size=26))
    pen.rectangle((0, 282, 319, 319), fill=165)  # the data bar's frame
    pen.rectangle((4, 286, 315, 315), fill=248)
    pen.text((10, 290), "EHT = 3.00 kV   WD = 4.0 mm   Mag = 8.02 K X", fill=0, font=ImageFont.load_default(size=11))
    pen.rectangle((10, 308, 60, 310), fill=0)  # its scale bar
    buffer = io.BytesIO()
    canvas.save(buffer, format="JPEG", quality=75)
    return np.asarray(Image.open(buffer), np.float32) / 255, 28.0


@pytest.mark.parametrize("polarity", ["bright", "dark"])
def test_a_data_bar_and_a_label_box_with_frames_are_not_particles(polarity):
    image, diameter = figure_crop(polarity)
    mask = annotations.annotation_mask(image)
    assert mask[282:, :].mean() > 0.95 and mask[6:53, 6:53].mean() > 0.95  # bar and box with their frames
    assert mask[60:270, 60:310].mean() < 0.01  # the field itself is left alone
    params, labels, d = measured(image, polarity)
    assert not (labels > 0)[282:].any() and not (labels > 0)[6:53, 6:53].any()
    assert abs(np.median(d) / diameter - 1) < 0.1 and abs(params.scale / diameter - 1) < 0.15


def test_a_rod_is_one_particle_and_a_neck_still_splits():
    """A rod's ridge in the distance transform rises and falls a few % along its length (digitised, slightly uneven
    sides): every maximum min_distance apart seeds a piece of about its width. With neck_depth a seed must stand that
    share of its height above the saddle to a higher one: the rod stays whole, touching discs (a deep neck) split."""
    params = P.SegmentParams(scale=24, neck_depth=0.2).resolved()
    yy, xx = np.mgrid[:80, :160]
    for seed in range(3):
        rng = np.random.default_rng(seed)
        half_width = 10 + np.cumsum(rng.normal(0, 0.15, 160)).clip(-1.5, 1.5)  # sides uneven by up to 1.5 px
        angle = rng.uniform(-0.3, 0.3)
        along = (xx - 80) * np.cos(angle) + (yy - 40) * np.sin(angle)
        across = -(xx - 80) * np.sin(angle) + (yy - 40) * np.cos(angle)
        rod = (np.abs(along) <= 55) & (np.abs(across) <= half_width[np.clip(xx, 0, 159)])
        every_maximum = P.split_touching(rod, replace(params, neck_depth=0.0)).max()
        assert every_maximum >= 3, (seed, every_maximum)  # pieces of about the rod's width
        assert P.split_touching(rod, params).max() == 1, seed
    pair = (np.hypot(yy - 40, xx - 60) <= 12) | (np.hypot(yy - 40, xx - 82) <= 12)  # overlapping by 2 px
    assert P.split_touching(pair, params).max() == 2
    with pytest.raises(ConfigError, match="neck_depth"):
        P.SegmentParams(neck_depth=1.0)


def test_the_neck_caps_are_those_of_one_reconstruction_over_the_image():
    """`_neck_caps` works cluster by cluster (a threshold where a component holds one peak, its top; a
    reconstruction on the box of every other cluster): its seeds are those of one reconstruction over the whole
    image, with components touching diagonally (one a single pixel), pairs at necks, rods and lone discs."""
    from skimage.feature import peak_local_max

    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:120, :160]
    foreground = np.zeros((120, 160), bool)
    for _ in range(14):  # discs of 4-28 px, overlapping at random: lone discs, pairs and chains
        cy, cx, r = rng.uniform(0, 120), rng.uniform(0, 160), rng.uniform(2, 14)
        foreground |= np.hypot(yy - cy, xx - cx) <= r
    foreground[100:108, 4:60] = True  # a rod
    foreground[2:6, 2:6] = True  # a square and a pixel touching it at a corner only (8-, not 4-connected)
    foreground[6, 6] = True
    foreground[10:14, 10:14] = True  # two squares meeting at a corner
    foreground[14:18, 14:18] = True
    packed = np.hypot((yy % 20) - 10, (xx % 20) - 10) >= 3  # a film with round holes: one cluster over the image
    for field in (foreground, packed):
        components, _ = ndi.label(field)
        distance = ndi.distance_transform_edt(field)
        for min_distance in (2, 4):
            found = peak_local_max(distance, min_distance=min_distance, labels=components, exclude_border=False)
            peaks = np.zeros(field.shape, bool)
            peaks[tuple(found.T)] = True
            for depth in (0.1, 0.2, 0.5):
                expected = P.watershed._caps(distance, depth, peaks)
                np.testing.assert_array_equal(P.watershed._neck_caps(distance, depth, peaks, components), expected)
        assert ndi.label(expected)[1] < peaks.sum()  # the deepest caps merge seeds: the comparison is not idle


def test_thin_strands_are_not_cut_into_particle_sized_fragments():
    """A film wrinkle (a wavy strand 3-7 px wide): every local maximum of its distance transform along its length
    seeds a segment (the default); with seed_depth=1 only 1-px-deep maxima (h-maxima) do, so it stays a few pieces."""
    params = P.SegmentParams(scale=15, seed_depth=1.0, neck_depth=0.0).resolved()
    rows = np.arange(96)[:, None]
    for seed in range(4):
        rng = np.random.default_rng(seed)
        x = np.arange(140)
        middle = 48 + 10 * np.sin(x / 12.0) + np.cumsum(rng.normal(0, 0.4, x.size))
        half_width = 1.5 + np.abs(np.cumsum(rng.normal(0, 0.3, x.size))).clip(0, 2)
        strand = np.zeros((96, 160), bool)
        strand[:, 10:150] = np.abs(rows - middle) <= half_width
        every_maximum = len(P.segment_diameters(P.split_touching(strand, replace(params, seed_depth=0.0)), params))
        deep_maxima = len(P.segment_diameters(P.split_touching(strand, params), params))
        assert every_maximum >= 20 and deep_maxima <= every_maximum / 2.5, (seed, every_maximum, deep_maxima)
    yy, xx = np.mgrid[:64, :64]
    pair = (np.hypot(yy - 32, xx - 24) <= 8) | (np.hypot(yy - 32, xx - 40) <= 8)  # two touching discs stay two
    assert len(np.unique(P.split_touching(pair, params))) - 1 == 2
    assert P.SegmentParams().seed_depth == 0  # off by default (it merges touching TiO2 particles)
    with pytest.raises(ConfigError, match="seed_depth"):
        P.SegmentParams(seed_depth=-1)


def test_touching_particles_are_split():
    image, _, centres = discs(size=160, diameter=26, n=14, seed=3, gap=-3.0)  # neighbours overlap by up to 3 px
    _, labels, _ = measured(image, "bright")
    assert abs((len(np.unique(labels)) - 1) - len(centres)) <= 2


def test_a_particle_near_the_border_does_not_touch_it():
    """The smoothing must not mirror a particle across the image border: reflected, a 110 px particle 2 px from the
    border (smoothed at 6.4 px) and its mirror image blur across the gap, its segment reaches the border and it is
    not measured (the synthetic sweep's one miss: 384 px, two whole 110 px discs, one of them 2 px from the edge)."""
    size, d = 300, 110.0
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), 0.3)
    image[(yy - (2 + d / 2)) ** 2 + (xx - 60) ** 2 <= (d / 2) ** 2] += 0.35  # 2 px from the top border
    image[(yy - 220) ** 2 + (xx - 220) ** 2 <= (d / 2) ** 2] += 0.35
    image += 0.02 * np.random.default_rng(0).standard_normal((size, size))
    params = P.SegmentParams(scale=d).resolved()
    labels, _ = P.segment_particles(image.astype(np.float32), params, "bright")
    assert labels[0].max() == 0  # the top row stays background
    assert len(P.segment_diameters(labels, params)) == 2


def test_an_empty_field_fails_clearly():
    rng = np.random.default_rng(4)
    image = np.clip(0.4 + 0.05 * ndi.gaussian_filter(rng.standard_normal((160, 160)), 1.5) * 3, 0, 1)
    with pytest.raises(P.NoParticles, match=r"data\.segment\.scale"):
        P.resolve_params([image.astype(np.float32)], None, "bright")
    labels, foreground = P.segment_particles(image, None, "bright")  # callers that only ask get nothing, no error
    assert not labels.any() and not foreground.any()


def test_empty_folder_profile_says_what_was_tried_and_writes_the_figure(tmp_path, monkeypatch):
    from conftest import compose

    from drgan.profile import ProfileSettings, profile

    rng = np.random.default_rng(5)
    folder = tmp_path / "images"
    folder.mkdir()
    flat = np.clip(0.4 + 0.05 * rng.standard_normal((160, 160)), 0, 1)
    Image.fromarray((flat * 255).astype(np.uint8)).save(folder / "empty.png")
    monkeypatch.chdir(tmp_path)
    cfg = compose([f"data.dir={folder}", "name=empty", f"out={tmp_path / 'out'}", "patch_size=64"], "profile")
    with pytest.raises(DataError) as error:
        profile(ProfileSettings.from_config(cfg))
    message = str(error.value)
    assert "no particles found" in message and "data.segment.scale" in message and "data.polarity" in message
    assert "nan" not in message and "no consistent particle size" in message and "scales (6-" in message
    for figure in ("particles.png", "scale_search.png"):  # the images, and what the search saw
        assert (tmp_path / "out" / figure).stat().st_size > 0


def test_user_settings_are_kept_exactly():
    image, _, _ = discs(seed=6)
    given = P.SegmentParams(sigma=2.0, min_distance=9, min_area=50, max_area=900)
    params, estimate = P.resolve_params([image], given, "bright")
    assert (params.sigma, params.min_distance, params.min_area, params.max_area) == (2.0, 9, 50, 900)
    assert estimate is not None  # the scale (for the illumination and blobs) was still measured
    fixed = P.SegmentParams(scale=24.0).resolved()
    assert fixed.scale == 24.0 and fixed.min_distance == round(P.CALIBRATION.min_distance_per_diameter * 24)
    with pytest.raises(Exception, match="unknown key"):
        P.SegmentParams.from_config({"sigmaa": 1.0})


def test_16_bit_and_rgb_input_give_the_same_particles():
    image, _, _ = discs(seed=7, diameter=22)
    as16 = (image * 65535).astype(np.uint16)
    rgb = np.repeat((image * 255).astype(np.uint8)[..., None], 3, axis=2)
    scales = [P.resolve_params([x], None, "bright")[0].scale for x in (image, as16, rgb)]
    assert max(scales) / min(scales) < 1.05 and abs(scales[0] / 22 - 1) < 0.15
    counts = [len(np.unique(P.segment_particles(x, None, "bright")[0])) - 1 for x in (image, as16, rgb)]
    assert max(counts) - min(counts) <= 1


def _small_particles_among_specks() -> np.ndarray:
    """8 bright discs of 16 px and 100 bright specks of 4.6 px (just above min_area at the particles' scale): the
    specks outnumber the particles 12:1 but cover less area."""
    image, _, centres = discs(size=256, diameter=16, n=8, noise=0.02, seed=0, gap=10)
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:256, :256]
    taken = np.zeros(image.shape, bool)
    for c in centres:
        taken |= (yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= 12**2
    placed = 0
    while placed < 100:
        c = rng.uniform(6, 250, 2)
        if taken[int(c[0]), int(c[1])]:
            continue
        speck = (yy - c[0]) ** 2 + (xx - c[1]) ** 2 <= 2.3**2
        image[speck] = np.clip(image[speck] + 0.3, 0, 1)
        taken |= speck
        placed += 1
    return image


def test_small_particles_among_more_specks_are_the_scale_that_persists():
    """100 specks of 4.6 px among 16 px particles: the specks' own scale never holds (their median follows the
    smoothing), the particles' holds over many scales; the search settles at the particles."""
    image = _small_particles_among_specks()
    params, found = P.resolve_params([image], None, "bright")
    assert abs(params.scale / 16 - 1) < 0.1 and found.refined_px == pytest.approx(params.scale, abs=0.01)
    chosen = max(found.candidates, key=lambda f: f.evidence)
    assert chosen.basin >= 5 and abs(chosen.median / 16 - 1) < 0.15


def _on_map(monkeypatch, at, given=None, size=256):
    """resolve_params on a scripted scale map: ``at(scale, depth)`` gives the segments' numbers (a dict overriding
    median (NaN: none), weighted (default: the median), spread, segments, separability, lowest (default: the
    separability)) for every segmentation the search asks for. Returns (params, estimate, scales asked)."""
    asked = []

    def point(prepared, params, scale, depth):
        asked.append((round(scale, 2), depth))
        v = {"median": math.nan, "spread": 0.3, "segments": 12, "separability": 0.8, **at(scale, depth)}
        v.setdefault("weighted", v["median"])
        v.setdefault("lowest", v["separability"])
        return P.Point(round(scale, 2), depth, **v)

    monkeypatch.setattr(P.search, "_point", point)
    image = np.zeros((size, size), np.float32)
    params, estimate = P.resolve_params([image], P.SegmentParams(**(given or {})), "bright")
    return params, estimate, asked


def _specks_and_particles(particles: dict, specks: dict | None = None):
    """Specks whose median follows the scale up to 10 px (a fixed point at each grid scale there, each holding over
    one), particles of 40 px at every scale from 14 to 100 px (one fixed point holding over ~12), agglomerates above."""

    def at(scale, depth):
        if scale <= 10.5:
            return {"median": scale, "separability": 0.9, "spread": 1.6, "segments": 400, **(specks or {})}
        if scale < 14:
            return {"median": 0.5 * scale}
        if scale <= 100:
            return {"median": 40.0, **particles}
        return {"median": 2 * scale}

    return at


def test_the_scale_that_persists_wins_over_one_that_separates_better(monkeypatch):
    # the former rule (separability + 0.05 per doubling) chose the specks: 0.9 + 0.05 log2 6 > 0.75 + 0.05 log2 40
    params, estimate, asked = _on_map(monkeypatch, _specks_and_particles({"separability": 0.75}))
    assert params.scale == pytest.approx(40, abs=0.5) and params.neck_depth == 0.0 and not estimate.alike
    assert params.min_separability == P.CALIBRATION.min_separability
    scales = {f.scale: f for f in estimate.candidates if f.depth == 0.0}
    assert scales[6.0].basin <= 2 and scales[40.36].basin >= 12  # the specks and the particles
    assert estimate.grid and len({s for s, _ in asked}) >= len(P.scale_grid((256, 256)))
    # a small change away from both fixed points (here: the specks separating even better) changes nothing
    again, _, _ = _on_map(monkeypatch, _specks_and_particles({"separability": 0.75}, {"separability": 0.97}))
    assert again.scale == params.scale


def test_a_fixed_point_below_min_separability_is_a_candidate_when_its_segments_are_alike(monkeypatch):
    """A dense packing of textured particles: their narrow gaps separate at 0.55-0.65, their texture's specks
    better. Alike segments (spread <= ALIKE_SPREAD, or <= ALIKE_SHARE of the specks' spread), ALIKE_SEGMENTS of them,
    separating ALIKE_SEPARABILITY on every image make the fixed point a candidate; the final min_separability is
    lowered to what it separated."""
    alike = {"separability": 0.6, "lowest": 0.583, "spread": 0.3, "segments": 12}
    params, estimate, _ = _on_map(monkeypatch, _specks_and_particles(alike))
    assert params.scale == pytest.approx(40, abs=0.5) and estimate.alike and params.min_separability == 0.58
    # alike by comparison: 0.7 is less than half the specks' spread of 1.6, and more than half of 1.2
    params, estimate, _ = _on_map(monkeypatch, _specks_and_particles({**alike, "spread": 0.7}))
    assert params.scale == pytest.approx(40, abs=0.5) and estimate.alike
    params, estimate, _ = _on_map(monkeypatch, _specks_and_particles({**alike, "spread": 0.7}, {"spread": 1.2}))
    assert params.scale == 6.0 and not estimate.alike
    for other in (
        {**alike, "spread": 0.9},  # not alike enough: more than half the specks' spread
        {**alike, "lowest": 0.5},  # one image separates too little
        {**alike, "segments": 4},  # too few segments
    ):
        params, estimate, _ = _on_map(monkeypatch, _specks_and_particles(other))
        assert params.scale == 6.0 and not estimate.alike and params.min_separability == 0.66, other
    # a min_separability set by hand is kept: no alike candidate below it
    params, estimate, _ = _on_map(monkeypatch, _specks_and_particles(alike), {"min_separability": 0.62})
    assert params.scale == 6.0 and not estimate.alike and params.min_separability == 0.62


def test_no_fixed_point_separating_enough_is_no_particles(monkeypatch):
    def at(scale, depth):
        return {"median": scale, "separability": 0.62, "spread": 1.5}

    with pytest.raises(P.NoParticles, match=r"no consistent particle size: \d+ scale\(s\).*at most 0.62.*needed 0.66"):
        _on_map(monkeypatch, at)
    with pytest.raises(P.NoParticles, match="at no scale were the segments of its own size"):
        _on_map(monkeypatch, lambda scale, depth: {"median": 0.4 * scale})


def test_the_area_weighted_median_where_the_plain_one_agrees_nowhere(monkeypatch):
    # specks outnumbering a few particles hold the plain median at a third of every scale; their share of the area
    # is small, and the area-weighted median holds at the particles'
    def at(scale, depth):
        return {"median": scale / 3, "weighted": 24.0 if scale >= 10 else scale / 3, "spread": 1.2}

    params, estimate, _ = _on_map(monkeypatch, at)
    assert params.scale == 24.0
    assert all(f.median == 24.0 for f in estimate.candidates)  # the plain map found none


def test_fixed_points_the_grid_steps_over_and_above_its_top_are_found(monkeypatch):
    # segments 1.4x their scale up to 28 px and 0.7x from 34 px: the map crosses its diagonal between two grid
    # scales, where it is segmented too
    def crossing(scale, depth):
        if 28.6 < scale < 33.9:
            return {"median": scale}
        return {"median": 1.4 * scale if scale <= 28.6 else 0.7 * scale}

    params, estimate, asked = _on_map(monkeypatch, crossing)
    assert 28.6 < params.scale < 33.9 and any(28.6 < s < 33.9 for s, _ in asked)
    # particles larger than half the image: the top scale's segments are still larger, and the map is followed up
    params, estimate, asked = _on_map(monkeypatch, lambda scale, depth: {"median": min(1.5 * scale, 200.0)})
    assert abs(params.scale / 200 - 1) < 0.1 and max(s for s, _ in asked) > P.scale_grid((256, 256))[-1]


@pytest.mark.parametrize(
    "deep, expected",
    [
        ({"spread": 0.1}, P.CALIBRATION.neck_depth),  # merged at necks, far more alike: rods whole
        ({"spread": 0.7}, 0.0),  # merged, no more alike: touching particles merged
    ],
)
def test_seeds_at_necks_need_more_alike_sizes_not_only_persistence(monkeypatch, deep, expected):
    # with seeds at necks the particles hold over every scale (basin 19), with every maximum seeding over a few;
    # persistence alone would always merge
    def at(scale, depth):
        if depth == 0.0:
            return {"median": 30.0 if 24 <= scale <= 40 else 0.6 * scale, "spread": 0.8}
        return {"median": 30.0, **deep}

    params, estimate, _ = _on_map(monkeypatch, at)
    assert params.neck_depth == expected and abs(params.scale / 30 - 1) < 0.1
    assert estimate.depth == expected


def _small_on_noise(plateau_until: float):
    """Particles of ~7.3 px on a noisy film (EMPS ed3a3cb76b): at their own scale the noise's specks join them and
    nothing separates enough; smoothed as for 12 px and more they separate and come out at their size up to
    ``plateau_until``, larger agglomerates of them above."""

    def at(scale, depth):
        if scale < 11:
            return {"median": scale, "separability": 0.65, "spread": 1.0}
        if scale <= plateau_until:
            return {"median": 7.2 * (scale / 12) ** 0.1, "separability": 0.7}
        return {"median": 0.6 * scale, "separability": 0.7}

    return at


def test_particles_separating_only_when_smoothed_more_are_a_plateau(monkeypatch):
    params, estimate, _ = _on_map(monkeypatch, _small_on_noise(plateau_until=30))
    assert (
        params.scale == 12.0 and params.min_separability == P.CALIBRATION.min_separability
    )  # the least smoothing separating
    plateau = [f for f in estimate.candidates if f.scale == 12.0]
    assert plateau and plateau[0].median == pytest.approx(7.2) and plateau[0].basin == 6  # 12 to 28.5 px
    # a size held over fewer than PLATEAU_SCALES (12 to 20 px: four) is no plateau: noise's specks do that
    with pytest.raises(P.NoParticles):
        _on_map(monkeypatch, _small_on_noise(plateau_until=21))


def test_candidates_go_to_json_and_back_including_those_written_before_the_plateau():
    f = P.Fixed(12.0, 0.0, 7.23, 0.694, 0.694, math.nan, 22, 6, False, True)
    assert json.loads(json.dumps(f.as_list()))[5] is None  # NaN spread: null
    back = P.Fixed.from_list(json.loads(json.dumps(f.as_list())))
    assert back.plateau and math.isnan(back.spread) and back._replace(spread=0.0) == f._replace(spread=0.0)
    older = P.Fixed.from_list([28.54, 0.0, 28.1, 0.81, 0.8, 0.52, 40, 9, False])  # a profile.json of last month
    assert not older.plateau and older.basin == 9


def test_area_weighted_median_by_hand():
    assert P.area_weighted_median(np.array([1.0, 1.0, 1.0, 10.0])) == 10.0  # areas 1, 1, 1, 100
    assert P.area_weighted_median(np.array([3.0, 4.0])) == 4.0  # 9 of 25 below 4
    assert P.area_weighted_median(np.array([5.0, 5.0, 5.0])) == 5.0


def test_the_search_reports_the_separability_of_the_scale_it_returns():
    """The search returns scales it segmented with and those segmentations' separabilities: the final
    segmentation at the returned scale passes (or fails) min_separability exactly as the search saw it (returning
    the next scale with the previous one's separability left grainy images with a scale and no particle)."""
    image, _, _ = discs(size=256, diameter=30, n=8, polarity="dark", noise=0.06, grain=1.5, seed=5)
    prepared = [P.prepare(image, "dark", True)]
    chosen, fixed, _ = P.search_scale(prepared, P.SegmentParams())
    assert len(fixed) >= 2
    for f in [chosen, *fixed]:
        at_scale = P.cut_foreground(prepared[0], replace(P.SegmentParams(), min_separability=0.0).resolved(f.scale))
        assert f.separability == pytest.approx(at_scale.separability, abs=1e-9), f


def test_blob_centres_are_the_particles_not_the_grain():
    """A few particles on a grainy film: the significant centres are the particles' (most LoG maxima there are
    grain); densely packed touching particles keep one centre each by default."""
    for seed in (6, 7):
        image, _, centres = discs(size=256, diameter=24, n=6, noise=0.08, grain=1.5, seed=seed, gap=20)
        assert P.blob_centres(image, 24.0).sum() > 2 * len(centres)  # without the film's noise: grain maxima too
        found = np.argwhere(P.blob_centres(image, 24.0, significant=True))
        assert abs(len(found) - len(centres)) <= 1, (seed, len(found))
        truth = np.array(centres)
        assert all(np.hypot(*(truth - f).T).min() <= 6 for f in found)
    image, _, centres = discs(size=160, diameter=26, n=14, seed=3, gap=-3.0)
    assert abs(int(P.blob_centres(image, 26.0).sum()) - len(centres)) <= 1


def _with_specks(image: np.ndarray, centres: list, radius: float, contrast: float, n: int = 12) -> np.ndarray:
    """``image`` with n bright specks (discs of ``radius`` px) at least 24 px from every particle centre."""
    yy, xx = np.mgrid[: image.shape[0], : image.shape[1]]
    near = np.zeros(image.shape, bool)
    for c in centres:
        near |= np.hypot(yy - c[0], xx - c[1]) <= 24
    rng, placed = np.random.default_rng(9), 0
    while placed < n:
        c = rng.uniform(8, image.shape[0] - 8, 2)
        speck = np.hypot(yy - c[0], xx - c[1]) <= radius
        if (speck & near).any():
            continue
        image[speck] += contrast
        near |= np.hypot(yy - c[0], xx - c[1]) <= 12
        placed += 1
    return image


@pytest.mark.parametrize("seed", [10, 11])
def test_a_few_particles_on_grain_are_found_and_grain_specks_are_not(seed):
    """Six particles on a grainy film at their known scale: every one found (with the Otsu region around the grain's
    LoG maxima too, the separability fell below min_separability and nothing was: now it is taken again around the
    blobs that stand out of the film's noise), and bright specks of 7 px far from them, past the threshold and above
    min_area, are not foreground (at most one reaches a centre)."""
    params = P.SegmentParams(scale=24).resolved()
    image, _, centres = discs(size=256, diameter=24, n=6, noise=0.08, grain=2.5, seed=seed, gap=30)
    bright = P.prepare(image, "bright", True).bright
    smooth = ndi.gaussian_filter(bright, params.sigma, mode="reflect")
    plain = P.foreground._threshold(
        smooth, P.blob_centres(bright, params.scale), np.zeros(image.shape, bool), params.scale
    )
    assert plain[1] < params.min_separability  # around every LoG maximum: the grain's threshold
    foreground, separability = P.cut_foreground(P.prepare(image, "bright", True), params)[:2]
    assert separability >= params.min_separability and ndi.label(foreground)[1] == 6
    assert all(foreground[int(c[0]), int(c[1])] for c in centres)

    image = _with_specks(image, centres, radius=3.5, contrast=0.3)
    foreground = P.cut_foreground(P.prepare(image, "bright", True), params).foreground
    assert all(foreground[int(c[0]), int(c[1])] for c in centres) and ndi.label(foreground)[1] <= 7


@pytest.mark.parametrize("seed", [10, 11])
def test_the_scale_of_a_few_particles_on_grain_is_found(seed):
    """No scale given: the search retries around the significant blobs as the final segmentation does (it segments
    with min_separability 0, and retried only below that, never: 'no particles found' on such images)."""
    image, _, centres = discs(size=256, diameter=24, n=6, noise=0.08, grain=2.5, seed=seed, gap=30)
    params, labels, d = measured(image, "bright")
    assert abs(params.scale / 24 - 1) < 0.1 and len(d) == len(centres) and abs(np.median(d) / 24 - 1) < 0.1


def _packing(diameter=40.0, size=(256, 320), seed=0):
    """Bright discs packed edge to edge (hexagonal, jittered) with pure black gaps, as SEM figures of monodisperse
    spheres show them: many gaps are character-sized black shapes near an edge."""
    rng = np.random.default_rng(seed)
    h, w = size
    yy, xx = np.mgrid[:h, :w]
    image = np.full(size, 0.02)
    r = diameter / 2
    for row, y in enumerate(np.arange(-r, h + r, diameter * np.sqrt(3) / 2)):
        for x in np.arange(-r + (row % 2) * r, w + r, diameter):
            dist = np.hypot(yy - y - rng.normal(0, 1.5), xx - x - rng.normal(0, 1.5))
            image[dist < r] = 0.5 + 0.3 * (dist[dist < r] / r) ** 2
    return np.clip(image + rng.normal(0, 0.01, size), 0, 1).astype(np.float32)


def test_the_black_gaps_of_a_dense_packing_are_not_text():
    canvas = Image.fromarray((_packing() * 255).astype(np.uint8))
    ImageDraw.Draw(canvas).text((4, 4), "(a)", fill=255, font=ImageFont.load_default(size=18))
    image = np.asarray(canvas, np.float32) / 255
    gaps = image <= annotations.ANNOTATION_LEVEL
    mask = annotations.annotation_mask(image)
    # the gaps inside the image hold character-shaped black groups as densely as the edges: the image's own, and
    # filling them from the spheres around would join the spheres (before: 14 % of the gap pixels masked)
    assert (mask & gaps).sum() < 0.01 * gaps.sum()
    assert mask[:24, :30].any()  # the white panel letter still is text


def test_a_scale_bars_label_is_text_among_black_specks_of_the_image():
    """Dark TEM particles with black specks inside: character-shaped black groups lie inside the image as densely as
    along its edges, so characters near the edges are the image's own (the dense-packing rule above), but the
    label beside the scale bar is text all the same (EMPS 5737e0c2c7: "200 nm" measured as two particles)."""
    image, _, centres = discs(size=256, diameter=30, n=10, polarity="dark", seed=5)
    rng = np.random.default_rng(5)
    for c in centres:  # three black specks (2 x 3 px) in each particle
        for dy, dx in rng.integers(-8, 7, (3, 2)):
            y, x = int(c[0]) + dy, int(c[1]) + dx
            image[y : y + 2, x : x + 3] = 0.0
    canvas = Image.fromarray((image * 255).astype(np.uint8))
    pen = ImageDraw.Draw(canvas)
    pen.fontmode = "1"  # solid strokes, as figures burn labels in
    pen.rectangle((150, 240, 240, 244), fill=0)  # the scale bar, bottom right
    pen.text((160, 218), "200 nm", fill=0, font=ImageFont.load_default(size=14))
    image = np.asarray(canvas, np.float32) / 255
    black = image <= annotations.ANNOTATION_LEVEL
    ink = np.zeros(image.shape, bool)
    ink[205:238, 155:240] = black[205:238, 155:240]
    mask = annotations.annotation_mask(image)
    assert mask[240:245, 150:241].all()  # the bar
    assert ink.sum() > 30 and mask[ink].all()  # its label (before: none of it)
    assert mask[:190][black[:190]].mean() < 0.05  # the specks in the particles stay the image's


def _rings(diameter=40.0, n=6, size=256, seed=3, rim=0.25):
    """Particles seen as bright rims around a centre as grey as the background (SEM edge effect, hollow shells)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    image = np.full((size, size), 0.3)
    r, centres = diameter / 2, []
    while len(centres) < n:
        c = rng.uniform(r + 4, size - r - 4, 2)
        if all(np.hypot(*(c - c2)) > 2 * r + 6 for c2 in centres):
            centres.append(c)
            dist = np.hypot(yy - c[0], xx - c[1])
            image[(dist <= r) & (dist >= (1 - rim) * r)] = 0.7
    return np.clip(image + rng.normal(0, 0.02, image.shape), 0, 1).astype(np.float32), centres


def test_a_rim_particle_is_one_particle_at_its_size():
    image, centres = _rings()
    params, labels, d = measured(image, "bright")
    # before: the rims were cut into arcs (154 segments, median 5 px)
    assert len(d) == len(centres) and abs(np.median(d) / 40 - 1) < 0.15
    assert all(labels[int(c[0]), int(c[1])] > 0 for c in centres)  # the centres belong to their particles


def test_only_round_holes_are_filled():
    params = P.SegmentParams(scale=40).resolved()
    yy, xx = np.mgrid[:200, :200]

    def disc(cy, cx, r):
        return (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r

    ring = disc(50, 50, 20) & ~disc(50, 50, 13)
    three = disc(150, 40, 20) | disc(150, 80, 20) | disc(150 - 34.64, 60, 20)  # touching: a concave gap between
    four = disc(40, 130, 20) | disc(40, 170, 20) | disc(80, 130, 20) | disc(80, 170, 20)  # a concave square gap
    filled = P.foreground._fill_holes(ring | three | four, params, np.zeros(ring.shape, bool))  # no marks
    assert filled[50, 50] and filled[disc(50, 50, 12)].all()  # the ring's centre is its particle's
    assert not filled[138, 60] and not filled[60, 150]  # the gaps among touching particles stay background
    assert (filled & ~(ring | three | four)).sum() == (disc(50, 50, 13) & ~ring).sum()


def test_no_blob_standing_out_is_no_proof_of_no_particles(monkeypatch):
    # where particles fill the image (a dense layer of rods), they are the LoG response's own spread and none stands
    # out of it: the search still runs from its fixed starts (before: "no blob stood out", an error)
    image, _, _ = discs(size=192, diameter=24, n=14, seed=4)
    nothing = P.ScaleEstimate(None, 0, 0.0, (3.0, 96.0))
    monkeypatch.setattr(P.search, "estimate_scale", lambda *args, **kwargs: nothing)
    params, estimate = P.resolve_params([image], None, "bright")
    assert abs(params.scale / 24 - 1) < 0.15 and estimate.diameter_px is None and estimate.refined_px is not None
    with pytest.raises(P.NoParticles, match="no blob stood out.*no consistent particle size"):
        P.resolve_params([np.full((96, 96), 0.5, np.float32)], None, "bright")


def test_a_retry_that_separates_worse_is_not_kept(monkeypatch):
    # Below min_separability the threshold is taken again around the blobs standing out of the film's noise. On a
    # dense packing none does (the "film" is the gaps and the particles' sides): the retry has nothing to threshold
    # and must not replace the first cut, else the scale search sees "no particle" at the particles' own scale.
    image, _, _ = discs(size=160, diameter=24, n=12, seed=2)
    params = P.SegmentParams(scale=24, min_separability=0.0).resolved()
    prepared = P.prepare(image, "bright")
    first = P.cut_foreground(prepared, params)  # min_separability 0: never retried
    assert first.separability > 0.7 and first.foreground.any()
    monkeypatch.setattr(P.foreground, "out_of_film_noise", lambda bright, response, centres: np.zeros_like(centres))
    retried = P.cut_foreground(prepared, params, retry_below=0.99)  # retried, and the retry finds no blob
    assert retried.separability == first.separability
    np.testing.assert_array_equal(retried.foreground, first.foreground)
    assert P.search._point([prepared], P.SegmentParams(min_separability=0.99), 24.0, 0.0).separability > 0.7


@pytest.mark.parametrize("min_separability", [0.58, 0.5, 0.66, 0.7])
def test_a_lowered_threshold_retries_where_the_scale_search_did(monkeypatch, min_separability):
    # The first cut separates at 0.62, the retry around the significant blobs at 0.64: the scale search retries below
    # the default 0.66, and the final segmentation with the threshold it lowered (0.58) must segment what it measured
    image, _, _ = discs(size=128, diameter=24, n=6, seed=1)
    prepared = P.prepare(image, "bright")
    seen = []

    def threshold(smooth, centres, annotations, scale):
        seen.append(int(centres.sum()))
        cut = real(smooth, centres, annotations, scale)
        return cut._replace(separability=0.62 if len(seen) == 1 else 0.64)

    real = P.foreground._threshold
    monkeypatch.setattr(P.foreground, "_threshold", threshold)
    monkeypatch.setattr(P.foreground, "out_of_film_noise", lambda bright, response, centres: centres)
    params = P.SegmentParams(scale=24, background=0, min_separability=min_separability).resolved()
    cut = P.cut_foreground(prepared, params)
    assert len(seen) == 2 and cut.separability == 0.64
    assert P.retry_separability(params) == max(min_separability, P.CALIBRATION.min_separability)
    seen.clear()  # the search's measurement: min_separability 0, retried as the final segmentation will be
    measured = P.search._measure(
        P.prepare(image, "bright"), replace(params, min_separability=0.0), P.retry_separability(params)
    )
    assert measured.separability == cut.separability


def _rods_and_pairs(kind: str, seed: int = 0, size: int = 224) -> tuple[np.ndarray, int]:
    """(bright image, particles): ``rods`` 12 px wide and 56-64 px long with sides uneven by up to 1.5 px, or
    ``pairs`` of 26 px discs overlapping by half a radius (a neck 0.13 of their radius deep) beside single discs."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    image, placed = np.full((size, size), 0.3), []
    for _ in range(400):
        if len(placed) == 8:
            break
        c = rng.uniform(40, size - 40, 2)
        if any(np.hypot(*(c - c2)) < 62 for c2 in placed):
            continue
        placed.append(c)
        if kind == "rods":
            angle, length = rng.uniform(0, np.pi), rng.uniform(56, 64)
            along = (xx - c[1]) * np.cos(angle) + (yy - c[0]) * np.sin(angle)
            across = -(xx - c[1]) * np.sin(angle) + (yy - c[0]) * np.cos(angle)
            half_width = 6 + np.cumsum(rng.normal(0, 0.15, size)).clip(-1.5, 1.5)
            shape = (np.abs(along) <= length / 2) & (np.abs(across) <= half_width[np.clip(xx, 0, size - 1)])
        else:
            offset = 6.5 * np.array([np.cos(a := rng.uniform(0, np.pi)), np.sin(a)]) * (len(placed) % 2)
            shape = np.zeros((size, size), bool)
            for centre in (c - offset, c + offset):
                shape |= np.hypot(yy - centre[0], xx - centre[1]) <= 13
        image[shape] = 0.65
    image += 0.02 * rng.standard_normal((size, size))
    n = len(placed) if kind == "rods" else len(placed) + (len(placed) + 1) // 2  # the odd ones are pairs
    return np.clip(image, 0, 1).astype(np.float32), n


@pytest.mark.parametrize("kind", ["rods", "pairs"])
def test_the_neck_depth_is_chosen_by_how_alike_the_sizes_come_out(kind):
    """neck_depth left None: rods cut into pieces of every length along their ridge are merged whole (their sizes
    alike), touching discs merged at their shallow necks would make singles and pairs, so they stay split."""
    image, n = _rods_and_pairs(kind)
    params, estimate = P.resolve_params([image], None, "bright")
    labels, _ = P.segment_particles(image, params, "bright")
    assert params.neck_depth == (P.CALIBRATION.neck_depth if kind == "rods" else 0.0), estimate.candidates
    assert estimate.depth == params.neck_depth
    assert labels.max() == n, (kind, labels.max(), n)
    assert {f.depth for f in estimate.candidates} == {
        0.0,
        P.CALIBRATION.neck_depth,
    }  # both depths found a particle size
    given = P.resolve_params([image], P.SegmentParams(neck_depth=0.0), "bright")[0]
    assert given.neck_depth == 0.0  # a depth given is kept


def _spheres(edge: str, size: int = 224, diameter: float = 40.0, n: int = 10, seed: int = 0) -> np.ndarray:
    """Dark particles in transmission, exp(-1.2 thickness) on a 0.75 film, blurred 1 px, noise 0.02: spheres
    ("dome": the projected thickness sqrt(1 - r^2 / R^2) falls to nothing at the outline) or flat discs ("step")."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    thickness, centres, r = np.zeros((size, size)), [], diameter / 2
    while len(centres) < n:
        c = rng.uniform(r + 2, size - r - 2, 2)
        if all(np.hypot(*(c - c2)) > 2 * r + 4 for c2 in centres):
            centres.append(c)
            q = 1 - ((yy - c[0]) ** 2 + (xx - c[1]) ** 2) / r**2
            thickness = np.maximum(thickness, np.sqrt(q.clip(0)) if edge == "dome" else (q >= 0).astype(float))
    image = ndi.gaussian_filter(0.75 * np.exp(-1.2 * thickness), 1.0) + 0.02 * rng.standard_normal((size, size))
    return np.clip(image, 0, 1).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1])
def test_outlines_lie_at_the_particles_steepest_edge(seed):
    """Otsu's threshold outlines a sphere inside its edge (its contrast falls off towards the outline); the
    segments are grown out to the level of the strongest edges. A flat disc's edge is where Otsu cuts: it stays."""
    sizes = {}
    for edge in ("dome", "step"):
        image = _spheres(edge, seed=seed)
        params, _ = P.resolve_params([image], None, "dark")
        labels, foreground = P.segment_particles(image, params, "dark")
        cut = P.cut_foreground(P.prepare(image, "dark"), params)
        otsu = P.segment_diameters(P.split_touching(cut.foreground, params), params)
        grown = P.segment_diameters(labels, params)
        assert len(grown) == len(otsu) == 10  # grown, none merged, none added
        assert foreground.sum() >= cut.foreground.sum() and (foreground | ~cut.foreground).all()
        sizes[edge] = np.median(otsu) / 40, np.median(grown) / 40
    assert sizes["dome"][0] < 0.94 and sizes["dome"][1] > sizes["dome"][0] + 0.025  # Otsu's inside, grown out
    assert abs(sizes["dome"][1] - 1) < 0.05 and abs(sizes["step"][1] - 1) < 0.02
    assert sizes["step"][1] - sizes["step"][0] < 0.015


def test_outlines_not_grown_when_told():
    image = _spheres("dome")
    params = replace(P.resolve_params([image], None, "dark")[0], grow_outlines=False)
    labels, foreground = P.segment_particles(image, params, "dark")
    cut = P.cut_foreground(P.prepare(image, "dark"), params)
    assert (foreground == cut.foreground).all() and (labels == P.split_touching(cut.foreground, params)).all()
    assert (P.particle_foreground(image, params, "dark") == cut.foreground).all()
    with pytest.raises(ConfigError, match="grow_outlines"):
        P.SegmentParams(grow_outlines="yes")


def test_only_segments_of_plausible_area_grow():
    """A watershed sliver or speck below min_area keeps its pixels (grown, hundreds of them on a textured film
    would count as particles); a particle beside it grows out to its edge."""
    yy, xx = np.mgrid[:128, :128]
    dome = lambda r0, c0, r: np.sqrt((1 - ((yy - r0) ** 2 + (xx - c0) ** 2) / r**2).clip(0))  # noqa: E731
    smooth = ndi.gaussian_filter(dome(64, 50, 24) + dome(64, 100, 7), 1.5).astype(np.float32)
    threshold = 0.5
    foreground = smooth > threshold
    labels = ndi.label(foreground)[0]
    areas = np.bincount(labels.ravel())
    min_area = int(areas[2]) + 1  # the small dome is a speck
    cut = P.Cut(foreground, 0.9, np.zeros_like(foreground), smooth, threshold)
    grown, extent = P.grow_to_edges(cut, labels, 48.0, min_area, np.zeros_like(foreground))
    assert np.bincount(grown.ravel(), minlength=3)[1] > 1.1 * areas[1]  # the particle grew
    assert ((grown == 2) == (labels == 2)).all() and (extent == (grown > 0)).all()  # the speck did not
