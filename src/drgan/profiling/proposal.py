"""The material config `python -m drgan.profile` proposes from what it measured: the closest paper material as
parent (`choose_parent`), the measured keys over it (`material_settings`), the segmentation and mining settings
training should use (`data_settings`), a measured edge fringe (`fringe_settings`) and stage limits wide enough for
the images' background (`stage_limits`), each with why it was set; `material_yaml` writes it as
drgan_conf/material/NAME.yaml, checked against the typed material first.
"""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import numpy as np
from omegaconf import OmegaConf

from drgan.data import measurements
from drgan.data.classical import CALIBRATION, Fixed
from drgan.data.measurements import VIEW_EXTENT_FRACTION
from drgan.data.particle_edge import MAX_SATURATED

if TYPE_CHECKING:
    from drgan.profiling.result import ProfileResult

NOISE_LIMIT_FACTOR, NOISE_LIMIT_FLOOR = 2.2, 0.01  # every profiled material: noise_sigma.max = 2.2 x measured
EXTENT_PER_DIAMETER = 1.1  # largest extent / equivalent diameter of a particle seen from above (TiO2: 30 / 26.5 px)

PAPER_SIZES = {"tio2_sem": 30.0, "tio2_him": 40.0}


def choose_parent(polarity: str, kind: str, median_px: float) -> tuple[str, str]:
    """(paper material, why): dark particles -> tio2_tsem (transmission); bright rods -> agnw_sem, bright spheres
    -> sio2_him, other bright shapes -> the TiO2 material of the nearer particle size."""
    if polarity == "dark":
        return "tio2_tsem", "dark particles on a bright background: the transmission material"
    if kind == "rod":
        return "agnw_sem", "bright, elongated (axis ratio > 2.5): the wire material"
    if kind == "sphere":
        return "sio2_him", "bright, round (axis ratio < 1.3): the sphere material"
    parent = min(PAPER_SIZES, key=lambda k: abs(math.log(median_px / PAPER_SIZES[k])))
    return parent, f"bright, irregular: the TiO2 material of the nearest size ({PAPER_SIZES[parent]:.0f} px)"


def data_settings(result: ProfileResult) -> tuple[dict, dict]:
    """(data keys, notes): the segmentation the profile validated (data.segment, so that training mines with the
    same lengths) and data.min_particles when too few windows hold the default 3 particles (large particles)."""
    seg, counts = result.segmentation, result.particles_per_patch
    given = seg.setting
    # the lengths (from the scale or given), and any other key given by hand (neck_depth, min_separability, ..)
    data = {"segment": {k: v for k, v in seg.params.items() if k in SEGMENT_KEYS or k in given}}
    estimate = seg.scale_estimate
    log_scale = (
        "no LoG blob stood out (particles fill the image), a diameter searched from 8 px up,"
        if estimate is None or estimate["diameter_px"] is None
        else f"LoG blob scale {estimate['diameter_px']} px,"
    )
    if "scale" in given:
        how = "set by hand (data.segment)"
    elif estimate.get("plateau"):
        size = result.sizes.median_diameter_px
        how = (
            f"measured: {log_scale} no scale agreed with its segments' size and separated enough; from "
            f"{estimate['refined_px']} px up the segments keep one size ({size:.1f} px) over an octave and more: "
            "small particles that separate from a noisy film only when smoothed more than their size asks (the "
            "scale sets the smoothing; the sizes are the segments')"
        )
    else:
        how = f"measured: {log_scale} refined to the segments' own median ({estimate['refined_px']} px)"
    notes = {
        "data.segment.scale": f"particle diameter {seg.scale_px} px, {how}",
        "data.segment (sigma, min_distance, min_area, max_area, background)": "from the scale unless set by hand"
        + (f" ({', '.join(sorted(given))} given)" if given else "")
        + f"; Otsu separability {seg.separability_median:.2f} (particles segmented: {seg.particles})",
    }
    notes["data.segment.neck_depth"] = _neck_note(seg.params["neck_depth"], "neck_depth" in given, estimate)
    lowered = seg.params["min_separability"]
    if lowered != CALIBRATION.min_separability and "min_separability" not in given:
        data["segment"]["min_separability"] = lowered
        notes["data.segment.min_separability"] = (
            f"{lowered} (default {CALIBRATION.min_separability}): the particles' scale separates less than a "
            "finer one, but its segments are far more alike in size (a dense packing of textured particles: narrow "
            "gaps, texture cut into specks of every size at the finer scale); to decide, set data.segment.scale "
            "and data.segment.min_separability together"
        )
    notes["data.segment.grow_outlines"] = _outline_note(seg.params, seg.outlines_grown, result.data.images)
    enough = counts.with_3_or_more["windows"] / max(1, counts.windows)
    if enough < MIN_WINDOW_SHARE:
        data["min_particles"] = max(1, min(3, int(counts.median)))
        notes["data.min_particles"] = (
            f"{data['min_particles']}: only {100 * enough:.0f} % of the {counts.patch_size} px windows hold 3 or "
            f"more particles (median {counts.median:g})"
        )
    whole = counts.whole
    if whole is not None and whole["at_least_3"] < MIN_TRAIN_WINDOWS:
        # Training keeps windows showing data.min_particles *whole* particles: large or densely packed ones are
        # cut by most window edges (~100 px spheres: a few windows of a folder show 3 whole ones).
        k = next((k for k in (2, 1) if whole[f"at_least_{k}"] >= MIN_TRAIN_WINDOWS), 1)
        if k < data.get("min_particles", 3):
            data["min_particles"] = k
            notes["data.min_particles"] = (
                f"{k}: of the {whole['windows']} training windows ({counts.patch_size} px, stride {whole['stride']}) "
                f"{whole['at_least_3']} show 3 or more whole particles, {whole[f'at_least_{k}']} show {k} or more "
                f"(training wants at least {MIN_TRAIN_WINDOWS} to learn from)"
            )
    return data, notes


WHY_SEGMENT = {"scale": "measured", "neck_depth": "chosen by the segment sizes (note below)"}
SEGMENT_KEYS = ("scale", "sigma", "min_distance", "min_area", "max_area", "background", "neck_depth")
MIN_WINDOW_SHARE = 0.2  # below this share of windows with >= 3 particles, training mines windows with fewer
MIN_TRAIN_WINDOWS = 16  # ... and below this many windows with 3 whole particles (before near-duplicates go), too


def material_settings(result: ProfileResult, fits: list, chosen) -> tuple[str, str, dict, dict, dict]:
    """(parent, why, material, size, notes): what the profile measured, as the keys of a material inheriting the
    closest paper material (`choose_parent`), the size group's parameters for a bimodal fit (else {}), and per key
    why it was set."""
    parent, why = choose_parent(result.polarity.value, result.shape.mesh_kind, result.sizes.median_diameter_px)
    material, notes = _scene_keys(result, fits, chosen)
    imaging, imaging_notes = _imaging_keys(result, parent)
    material.update(imaging)
    notes.update(imaging_notes)
    size = _bimodal_size(chosen)
    if size:
        notes["size"] = f"the two lognormal components as normals (mean, std, px) x {EXTENT_PER_DIAMETER}"
    return parent, why, material, size, notes


def _scene_keys(result: ProfileResult, fits: list, chosen) -> tuple[dict, dict]:
    """The material's name, polarity, particle size and spread, particles per scene, mesh kind and Clark-Evans ratio,
    with why each was set."""
    polarity = result.polarity.value
    counts = result.particles_per_patch
    kind = result.shape.mesh_kind
    by_kind = {f.kind: f for f in fits}
    if chosen.kind == "normal":
        size_px, spread = chosen.params["mean"], chosen.params["std"] / chosen.params["mean"]
        spread_note = "std / mean of the normal fit"
    else:
        lognormal = by_kind["lognormal"].params
        size_px, spread = lognormal["median"], lognormal["sigma"]
        spread_note = "sigma of log(diameter), lognormal fit"
    # A material's sizes are largest extents (a mesh's scale); the profile measures equivalent diameters of
    # projected areas: ~0.9 x the largest extent for the paper's TiO2 particles (their masks against their meshes).
    size_px *= EXTENT_PER_DIAMETER
    # The constellations' range is that of the windows training keeps: those with data.min_particles particles (3,
    # or fewer for large or packed particles): the range of the few windows with 3 or more would render packed heaps
    # where the windows hold one or two particles.
    k = data_settings(result)[0].get("min_particles", 3)
    kept = (counts.kept_counts or {}).get(str(k)) or counts.with_3_or_more
    if not kept["windows"]:
        kept = {"p10": counts.p10, "p90": counts.p90}
    n_max = max(1, int(math.ceil(kept["p90"])))
    n_min = max(1, min(n_max, int(math.floor(kept["p10"]))))
    pol_note = "detected" if result.polarity.setting == "auto" else "set on the command line"
    material = {
        "name": result.name,
        "polarity": polarity,
        "particle_size_px": round(float(size_px), 1),
        "size_spread": round(float(spread), 3),
        "n_particles": n_max,
        "n_particles_min": n_min,
        "meshes": {"kind": kind},
    }
    notes = {
        "polarity": pol_note,
        "particle_size_px": f"median equivalent diameter of the segmented particles at half contrast (outlines "
        f"moved {result.sizes.outline_shift_px:+.2f} px) x {EXTENT_PER_DIAMETER} (a material's size is a particle's "
        "largest extent)",
        "size_spread": spread_note,
        "n_particles": f"p90 of particles per {counts.patch_size} px patch over the patches with >= {k} (those "
        f"training keeps, data.min_particles; mean over all patches {counts.mean:.1f})",
        "n_particles_min": "p10 over the same patches; a constellation draws n_particles_min..n_particles",
        "meshes.kind": f"median major/minor axis ratio {result.shape.axis_ratio_median:.2f}",
    }
    clark_evans = result.agglomeration.clark_evans_median
    if clark_evans is not None:
        material["clark_evans"] = round(float(clark_evans), 4)
        notes["clark_evans"] = (
            "median over the images of the segmented particles' Clark-Evans ratio (< 1 clustered); it decides "
            "drgan.segment's model.contact_weight=auto for bright particles"
        )
    return material, notes


def _imaging_keys(result: ProfileResult, parent: str) -> tuple[dict, dict]:
    """The keys of how the scene images: the noise bound, the window (large particles), the outline blur or the
    detector's grain, the stage's reach and the edge fringe, with why each was set."""
    counts = result.particles_per_patch
    material, notes = {}, {}
    background = result.background
    # The background shows the detector's noise: it bounds the learned noise for every parent. Without the bound an
    # SEM material's learned noise can rise to its parent's limit on clean images (experiments/pipeline/README.md).
    # A render with Monte Carlo grain adds its own on top of the learned noise.
    material["noise_sigma"] = {
        "min": 0.001,
        "max": round(max(NOISE_LIMIT_FLOOR, NOISE_LIMIT_FACTOR * background.noise_sigma), 4),
    }
    notes["noise_sigma.max"] = f"{NOISE_LIMIT_FACTOR} x the background's noise sigma (at least {NOISE_LIMIT_FLOOR})"
    render_px = counts.render_px or counts.patch_size  # render px per window; below the window: large particles
    if counts.render_px:
        material["view_width"] = int(counts.patch_size)
        notes["view_width"] = (
            f"{counts.patch_size} real px per training window, rendered at {render_px} px: the particles' median "
            f"extent ({EXTENT_PER_DIAMETER * result.sizes.median_diameter_px:.0f} px) would fill more of a "
            f"{render_px} px window than {VIEW_EXTENT_FRACTION:g} of it; the segmenter trained on the generated "
            "pairs resamples images by the same factor"
        )
    noiseless = parent_renders_without_sampling_noise(parent)  # a transmission scene: no Monte Carlo grain
    blur = filter_for_blur(result.edge_blur_px, render_px / counts.patch_size)
    if blur is not None and not noiseless:
        material["filter_stddev"] = blur
        notes["filter_stddev"] = (
            f"the outlines' measured blur {result.edge_blur_px:.2f} px (image px; {render_px / counts.patch_size:g} "
            "render px each) through the SEM renders' blur per filter (FILTER_FOR_BLUR)"
        )
    if noiseless:
        # Such a render has no Monte Carlo grain: the noise's spatial correlation is the detector's too (in render
        # px: a wide window's real grain is finer once area-averaged).
        material["noise_grain_px"] = round(float(background.grain_px) * render_px / counts.patch_size, 2)
        notes["noise_grain_px"] = (
            f"lag-1 autocorrelation {background.lag1_autocorrelation:.3f} of the background's high-pass residual"
        )
    stage = stage_limits(parent, background.background_grey)
    if stage is not None:
        material["imaging"] = {"stage_bsdf": {"base_color": stage[0]}}
        notes["imaging.stage_bsdf.base_color"] = stage[1]
    if parent_renders_fringe(parent):
        fringe, why_fringe = fringe_settings(result.edge)
        if fringe is not None:  # only a measured fringe: without one the material renders none
            material["imaging"] = {"fringe": fringe}
            notes["imaging.fringe"] = why_fringe
    return material, notes


def _bimodal_size(chosen) -> dict:
    """The size group's parameters for a bimodal fit: its two lognormal components as normals (largest extents);
    {} for another fit."""
    if chosen.kind != "bimodal":
        return {}
    p = chosen.params
    m1, s1 = (EXTENT_PER_DIAMETER * v for v in measurements.lognormal_to_normal(p["median1"], p["sigma1"]))
    m2, s2 = (EXTENT_PER_DIAMETER * v for v in measurements.lognormal_to_normal(p["median2"], p["sigma2"]))
    return {
        k: round(float(v), 3)
        for k, v in zip(("mean1", "std1", "mean2", "std2", "weight1"), (m1, s1, m2, s2, p["weight1"]))
    }


@functools.cache
def parent_material(parent: str) -> dict:
    """The paper material ``parent`` as plain values (composed once per process; callers do not modify it)."""
    from drgan.launch.configs import compose

    return OmegaConf.to_container(compose([f"material={parent}"], config_name="render").material, resolve=True)


@functools.cache
def parent_imaging(parent: str):
    """The paper material ``parent``'s imaging, typed (drgan.scene.config; typed once per process, read only)."""
    from drgan.scene.config import typed_material

    return typed_material(parent_material(parent)).imaging


def parent_renders_fringe(parent: str) -> bool:
    """Whether the parent material's imaging takes an edge fringe (``material.imaging.fringe``: transmission)."""
    return parent_imaging(parent).renders_fringe


FRINGE_LIMIT_FACTOR = 2.0  # a measured fringe's amplitude is learned within 0..2 x the fitted amplitude


def fringe_settings(edge: dict | None) -> tuple[dict | None, str]:
    """(``material.imaging.fringe`` or None, why): set only when the edge profile shows a ring (the rule of
    `drgan.data.particle_edge.find_ring`); its amplitude learned between 0 (no fringe) and FRINGE_LIMIT_FACTOR x the
    scene's fringe fitted to the profile (so training starts near the fit), its width the fit's. A ring the fit
    could not follow (too many bins saturated) is reported, not written."""
    if edge is None:
        return None, "no edge profile (too few isolated particles)"
    ring, fit = edge["ring"], edge["fringe"]
    if ring["kind"] == "none":
        return None, (
            f"none: the profile's extreme outside the edge, {-ring['height']:+.3f} of the particle contrast "
            f"(standard error {ring['height_se']:.3f}), is no ring by the rule"
        )
    kind = "opposite to" if ring["kind"] == "opposite" else "like"
    seen = (
        f"a ring {kind} the particles' grey {ring['distance_px']:.1f} px outside their edge, height "
        f"{ring['height']:+.3f} of the particle contrast (standard error {ring['height_se']:.3f})"
    )
    if fit is None:
        saturated = sum(share is not None and share > MAX_SATURATED for share in edge["saturated_share"])
        return None, f"{seen}, but the fringe could not be fitted ({saturated} of the bins saturated)"
    amplitude, width = fit["amplitude"], fit["width_px"]
    limit = round(FRINGE_LIMIT_FACTOR * amplitude, 4)
    fringe = {"amplitude": {"min": min(0.0, limit), "max": max(0.0, limit)}, "width_px": round(float(width), 2)}
    return fringe, (
        f"{seen}; fitted amplitude {amplitude:+.3f}, width {width:.2f} px (edge blur {fit['edge_blur_px']:.2f} "
        f"px); amplitude learned within 0..{FRINGE_LIMIT_FACTOR:g} x the fit"
    )


STAGE_REACH = 0.8  # the stage's limit widens when the images' background needs more than this of what it renders
STAGE_MARGIN = 4.0  # x the linear estimate of the stage value the background needs (the render saturates above it)
STAGE_CEILING = 5.0  # the particles' own limit in every paper material


@functools.cache
def parent_stage_reach(parent: str) -> tuple[float, float] | None:
    """(the parent material's stage base_color limit, the stage's grey rendered at it), or None for a scene without a
    lit stage (transmission). One render at spp 16 with the other learned values at the middle of their limits."""
    import torch

    from drgan.launch.configs import compose
    from drgan.models.gan_module import GANModule

    cfg = compose([f"material={parent}", "renderer.spp=16", "renderer.resolution=128"], config_name="train")
    module = GANModule.from_config(cfg)
    learned = module.generator.learned
    stage = [p for p in learned if p.key == "stage.base_color"]
    if not stage:
        return None
    values = torch.tensor([p.high if p is stage[0] else 0.5 * (p.low + p.high) for p in learned], dtype=torch.float32)
    phi = torch.as_tensor(module.sample_phi(1, seed=0)[0], dtype=torch.float32)
    with torch.no_grad():
        image = module.generator.render_one(phi, values, seed=1)[0].numpy()
    labels = module.generator.scene.instance_labels()
    return float(stage[0].high), float(image[labels == 0].mean())


def stage_limits(parent: str, background_grey: float) -> tuple[dict, str] | None:
    """``material.imaging.stage_bsdf.base_color`` limits wide enough for the images' background grey, with why; None
    when the parent's own limits reach it (or its scene has no lit stage). The paper SEM/HIM materials render their
    stage at most ~0.15 grey; SEM images with a mid-grey stage (~0.4) need a larger base colour, which the
    grey start (drgan.callbacks.grey_start) then finds within the widened limits."""
    reach = parent_stage_reach(parent)
    if reach is None:
        return None
    limit, grey = reach
    if background_grey <= STAGE_REACH * grey:
        return None
    high = round(min(STAGE_CEILING, limit * STAGE_MARGIN * background_grey / grey), 3)
    return {"min": 0.01, "max": high}, (
        f"0.01-{high}: the background is {background_grey:.3f} grey and {parent}'s stage renders at most {grey:.3f} "
        f"(limit {limit:g}); widened to {STAGE_MARGIN:g} x the linear estimate of the base colour the background needs"
    )


# The outline blur (measurements.edge_blur, render px) of SEM renders made with each reconstruction filter
# (material.filter_stddev): a profiled SEM material (tio2_him scene), 6 layouts each, the FCN at its initial values
# (experiments/pipeline/README.md, "outline blur"). A render's outline is never sharper than ~0.96 px (shading, the
# pixel's footprint); the paper's HIM materials' 3.0 renders 2.7 px.
FILTER_FOR_BLUR = ((0.96, 0.5), (1.12, 1.0), (1.52, 1.5), (1.96, 2.0), (2.69, 3.0))


def filter_for_blur(blur_px: float | None, render_per_image_px: float = 1.0) -> float | None:
    """The SEM renderer's filter_stddev whose renders have the images' outline blur (``blur_px``, image px;
    ``render_per_image_px`` converts it to render px), interpolated in FILTER_FOR_BLUR and held at its ends (0.5 for
    outlines sharper than any render, 3.0 for blurrier ones); None when no blur was measured."""
    if blur_px is None:
        return None
    blurs, filters = zip(*FILTER_FOR_BLUR)
    return round(float(np.interp(blur_px * render_per_image_px, blurs, filters)), 2)


FLAT_PILES = "poisson_flat"  # the placement group of clustered particles seen in transmission


def placement_group(parent: str, measured: str) -> str:
    """The placement group the material gets: the measured one, except that clustered particles seen in transmission
    get flat piles (conf/gan/placement/poisson_flat.yaml): a particle piled over another hides their contact there."""
    from drgan.scene.config import TransmissionImaging

    if measured == "poisson" and isinstance(parent_imaging(parent), TransmissionImaging):
        return FLAT_PILES
    return measured


def parent_lights_a_stage(parent: str) -> bool:
    """Whether the parent material's scene lights particles on a stage (secondary-electron imaging with a stage): where
    the integrator samples the stage's surface, hence where `FAST_INTEGRATOR` saves time."""
    from drgan.scene.config import SecondaryImaging

    imaging = parent_imaging(parent)
    return isinstance(imaging, SecondaryImaging) and imaging.stage


# The integrator a profiled secondary-electron material trains with: direct_light samples the BSDF as well as the
# lights on the particles (and on a stage whose roughness is learned or low) and only the lights on a rough stage of
# fixed roughness, one ray fewer per stage sample; the particles render alike, the GAN's steps run ~1.4 x faster, and
# the chain's segmenters score the same (experiments/pipeline/chain_time.md, "where the GAN's 20 minutes go"). The
# paper's SEM experiment trains with it too (conf/gan/experiment/tio2_sem.yaml).
FAST_INTEGRATOR = "direct_light"


def parent_renders_without_sampling_noise(parent: str) -> bool:
    """Whether the parent material's scene renders without Monte Carlo grain (its imaging config says so)."""
    return parent_imaging(parent).noiseless


def material_yaml(result: ProfileResult, fits: list, chosen) -> tuple[str, str]:
    """(parent name, the text of drgan_conf/material/NAME.yaml): the measured keys, checked against the typed
    material (`drgan.scene.config.typed_material`, merged over the parent) and dumped, with why each was set."""
    from drgan.scene.config import typed_material

    parent, why, material, size, notes = material_settings(result, fits, chosen)
    typed_material(
        OmegaConf.merge(parent_material(parent), material)
    )  # a value the schema refuses fails here, not in training
    agg, data = result.agglomeration, result.data
    notes["size group"] = f"{chosen.kind}: lowest BIC of normal / lognormal / bimodal"
    placement = placement_group(parent, agg.placement)
    notes["placement group"] = (
        f"{placement}: touching fraction {agg.touching_fraction:.2f}, Clark-Evans {agg.clark_evans_median}"
        + (
            " (clustered, flat piles: in transmission a piled particle hides its contact)"
            if placement == FLAT_PILES
            else ""
        )
    )
    body = {"material": material}
    if size:
        body["size"] = size
    render_px = result.particles_per_patch.render_px
    if render_px:  # a window wider than the render: area-averaged to it, for the real patches and the renders alike
        body["renderer"] = {"resolution": int(render_px)}
        notes["renderer.resolution"] = (
            f"{render_px} px: the wide windows are rendered (and the real ones area-averaged) at the profile's patch "
            f"size, {render_px / result.particles_per_patch.patch_size:g} x their real px; the generated pairs keep "
            "the factor (manifest pixel_scale) and the segmenter resamples your images by it"
        )
    if parent_lights_a_stage(parent):
        body.setdefault("renderer", {})["integrator"] = FAST_INTEGRATOR
        notes["renderer.integrator"] = (
            f"{FAST_INTEGRATOR}: the rough stage lit by light sampling alone (one ray fewer per stage sample); the "
            "particles render as with direct_light_mis"
        )
    segmentation, data_notes = data_settings(result)
    notes.update(data_notes)
    body["data"] = {
        "dir": data.dir,
        "crop_rows": data.crop_rows,
        "split": data.split,
        "polarity": material["polarity"],
        **segmentation,
    }
    header = [
        "# @package _global_",
        f"# Written by `python -m drgan.profile` from {data.images} image(s) of {data.dir}",
        f"# (report: {result.out}/report.md).",
        f"# Parent: {parent} ({why}); everything not set here comes from it, unmeasured.",
        "# Measured:",
        *(f"#   {key}: {note}" for key, note in notes.items()),
        f"#   for reference: background grey {result.background.background_grey:.3f}, noise sigma "
        f"{result.background.noise_sigma:.4f}",
        *(
            [f"#   edge fringe: {fringe_settings(result.edge)[1]}; the material renders none"]
            if parent_renders_fringe(parent) and "imaging" not in material
            else []
        ),
        "defaults:",
        f"  - {parent}",
        f"  - override /size: {chosen.kind}",
        f"  - override /placement: {placement}",
    ]
    return parent, "\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(body))


def _neck_note(depth: float, given: bool, estimate: dict | None) -> str:
    """Why the watershed's seeds have the neck depth they have (`drgan.data.classical.search_scale`)."""
    if given:
        return f"{depth}, set by hand"
    if estimate is None:
        return f"{depth}: the more alike segment sizes at the scale given (`drgan.data.classical.search_scale`)"
    fixed = [Fixed.from_list(c) for c in estimate.get("candidates", [])]

    def says(f: Fixed) -> str:
        spread = "one segment" if math.isnan(f.spread) else f"size spread log(q90/q10) {f.spread:.2f}"
        return f"{f.scale:.1f} px, holding over {f.basin} scales, {spread}"

    def best_of(d: float) -> Fixed | None:
        return max((f for f in fixed if f.depth == d), key=lambda f: f.evidence, default=None)

    mine, other = best_of(depth), best_of(CALIBRATION.neck_depth if depth == 0.0 else 0.0)
    what = "seeds at necks only" if depth else "every maximum seeding"
    head = f"{depth} ({what}): chosen with the scale"
    if mine is None:
        return head
    if other is None:
        return f"{head} ({says(mine)}); the other depth gave no particle size of its own"
    if (mine.scale, mine.segments, says(mine)) == (other.scale, other.segments, says(other)):
        return f"{head} ({says(mine)}); no neck shallow enough to merge: both depths segment alike"
    return (
        f"{head}: {says(mine)}, against {says(other)} with the other depth (seeds at necks only where they make the "
        "sizes more alike than every maximum seeding does: a rod cut along its ridge gives pieces of every length, "
        "touching particles merged give singles and pairs)"
    )


def _outline_note(params: dict, grown: dict | None, images: int) -> str:
    """What the outlines' growth to the particles' edges did (`drgan.data.classical.grow_to_edges`)."""
    if not params.get("grow_outlines", True):
        return "false (set by hand): Otsu's outlines"
    grown = grown or {"images": 0}
    if not grown["images"]:
        return f"true: on none of the {images} images did the strongest edges lie below Otsu's threshold"
    return (
        f"true: the outlines grew out to the particles' strongest edges, below Otsu's threshold, on {grown['images']} "
        f"of {images} images (foreground +{100 * grown['foreground_added_median']:.0f} %, median); false keeps Otsu's"
    )
