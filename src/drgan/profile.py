"""`python -m drgan.profile data.dir=DIR name=NAME`: profile unannotated particle images, write a material config.

Reads every (train) image, detects the polarity, segments the particles classically (drgan.data.profile), and
measures background grey, noise sigma and grain, the mean particle edge (and a defocus fringe on it), the diameter
distribution (normal / lognormal / two-lognormal mixture, chosen by BIC), particles per patch, agglomeration,
elongation and the pixel size. Writes, in `out` (default runs/profile/NAME): profile.json (every number),
report.md, sizes.png, scale_search.png (how the particle scale was found), particles.png (real images with the
detected outlines: keep them out of the repository), background_noise.png, edge_profile.png; and
./drgan_conf/material/NAME.yaml, a material inheriting the closest paper material, ready for
`python -m drgan.train material=NAME`.
"""

from __future__ import annotations

import functools
import logging
import math
import re
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from drgan.data import profile as est
from drgan.data.annotations import annotation_mask, as_grey
from drgan.data.classical import CALIBRATION, Fixed, NoParticles, SegmentParams, resolve_params
from drgan.data.images import default_split, list_images, read_grey, read_split
from drgan.data.patches import scale_sample
from drgan.data.polarity import check_polarity, resolve_polarity
from drgan.errors import ConfigError, DataError
from drgan.io import figure_png, write_bytes, write_json
from drgan.runtime import stage_main, start

log = logging.getLogger(__name__)


# --- settings and images ----------------------------------------------------------------------------------


NOISE_LIMIT_FACTOR, NOISE_LIMIT_FLOOR = 2.2, 0.01  # transmission materials: noise_sigma.max = 2.2 x measured
EXTENT_PER_DIAMETER = 1.1  # largest extent / equivalent diameter of a particle seen from above (TiO2: 30 / 26.5 px)


def _check_settings(cfg: DictConfig) -> tuple[Path, tuple[int, int] | None, str, int]:
    if not cfg.get("data") or not cfg.data.get("dir"):
        raise ConfigError("profile: give data.dir=DIR (a folder of particle images)")
    name = cfg.get("name")
    if not name or not re.fullmatch(r"[A-Za-z0-9_\-]+", str(name)):
        raise ConfigError(
            f"profile: name={name!r}: expected a material name of letters, digits, _ or - "
            "(the config is written as drgan_conf/material/NAME.yaml)"
        )
    from drgan.configs import shipped_materials

    if str(name) in shipped_materials():
        raise ConfigError(
            f"profile: name={name}: a material drgan ships has that name ({', '.join(shipped_materials())}); yours "
            f"would be confused with it on the config search path. Choose another name, e.g. name={name}_mine"
        )
    folder = Path(str(cfg.data.dir)).expanduser()
    if not folder.is_dir():
        raise ConfigError(f"profile: data.dir={folder}: no such folder (expected a folder of images)")
    crop = cfg.data.get("crop_rows")
    if isinstance(crop, str) and crop != "auto":
        raise ConfigError(f"profile: data.crop_rows={crop!r}: expected [start, stop), auto or null")
    if crop is not None and crop != "auto":
        crop = list(crop)
        if len(crop) != 2 or not all(isinstance(v, int) for v in crop) or not 0 <= crop[0] < crop[1]:
            raise ConfigError(f"profile: data.crop_rows={crop}: expected [start, stop) with 0 <= start < stop")
        crop = (crop[0], crop[1])
    polarity = check_polarity(cfg.data.get("polarity", "auto"), "data.polarity", allow_auto=True)
    patch = cfg.get("patch_size", 256)
    if not isinstance(patch, int) or patch < 16:
        raise ConfigError(f"profile: patch_size={patch}: expected an integer >= 16 px")
    max_images = cfg.get("max_images")
    if max_images is not None and (not isinstance(max_images, int) or max_images < 1):
        raise ConfigError(f"profile: max_images={max_images}: expected a positive integer or null")
    return folder, crop, polarity, patch


def resolve_split(folder: Path, split) -> Path | None:
    """data.split: auto (folder/split.json or folder/../split.json when present), a path, or None."""
    if split is None or str(split) in ("", "none", "null"):
        return None
    if str(split) == "auto":
        return default_split(folder)
    path = Path(str(split)).expanduser()
    if not path.is_file():
        raise ConfigError(f"profile: data.split={split}: no such file (expected a split.json, auto or null)")
    return path


def select_images(folder: Path, split_path: Path | None, max_images: int | None) -> list[Path]:
    """The images profiled: the split's train ids (never its test ids), else every image of the folder."""
    if split_path is None:
        paths = list_images(folder)
    else:
        split = read_split(split_path)
        if not split["train"]:
            raise DataError(f"split file {split_path}: empty 'train' list")
        paths = list_images(folder, split["train"])
        test = set(split["test"])
        assert not test & {p.stem for p in paths}, "read_split refuses overlapping splits"
    return paths[:max_images] if max_images else paths


# --- the profile ------------------------------------------------------------------------------------------


def profile(cfg: DictConfig) -> dict:
    """Profile the images of cfg.data.dir; write figures, profile.json, report.md and the material config."""
    folder, crop, polarity_setting, patch = _check_settings(cfg)
    name = str(cfg.name)
    conf_path = Path(str(cfg.get("conf_dir", "drgan_conf"))) / "material" / f"{name}.yaml"
    if conf_path.exists() and not cfg.get("overwrite", False):
        raise ConfigError(f"profile: {conf_path} exists; choose another name= or set overwrite=true")
    split_path = resolve_split(folder, cfg.data.get("split", "auto"))
    paths = select_images(folder, split_path, cfg.get("max_images"))
    images = [read_grey(p, crop) for p in tqdm(paths, desc="reading", unit="image")]  # checks crop on every image
    small = [p.name for p, im in zip(paths, images) if min(im.shape) < patch]
    if small:
        raise DataError(f"profile: image(s) {small[:3]} are smaller than patch_size={patch} px after cropping")

    polarity, estimate = resolve_polarity(polarity_setting, images)
    log.info("polarity: %s (%s)", polarity, "detected" if estimate else "set")

    # The particle scale (and from it every segmentation length), on the images mining searches it on (scale_sample);
    # data.segment keys given are kept as given.
    out = Path(str(cfg.out))
    setting = _segment_setting(cfg)
    try:
        params, scale = resolve_params(scale_sample(images), setting, polarity, progress=True)
    except NoParticles as error:
        _write_failure_figure(out, images, polarity, None)
        if error.search is not None:
            _scale_figure(out, error.search.as_dict())
        raise DataError(_nothing_found(folder, len(images), polarity, polarity_setting, error.what, out)) from None

    tables, foregrounds, labels_kept, counts, ce, separabilities, edges, grown = [], [], [], [], [], [], [], []
    for image in tqdm(images, desc="segmenting", unit="image"):
        labels, foreground, separability, added = est.segment_image(image, params, polarity)
        table = est.particle_table(labels)
        tables.append(table)
        foregrounds.append(foreground)
        separabilities.append(separability)
        grown.append(added)
        labels_kept.append(labels if len(labels_kept) < 4 else None)
        # The edge profile leaves out particles beside annotations (a scale bar may hide a neighbour).
        exclude = annotation_mask(as_grey(image)) if params.annotations else None
        edges.append(est.edge_samples(image, labels, foreground, exclude))
        counts.append(est.patch_counts(table["row"], table["col"], labels.shape, patch))
        ce.append(est.clark_evans(table["row"], table["col"], labels.size))
    if not sum(len(t["diameter_px"]) for t in tables):
        _write_failure_figure(out, images, polarity, labels_kept)
        what = (
            f"the particle scale {params.scale} px was found, but no segment of plausible area "
            f"({params.min_area}-{params.max_area} px^2) came out of the watershed (settings {params.as_dict()}; Otsu "
            f"separability {max(separabilities):.2f}, needed {params.min_separability})"
        )
        raise DataError(_nothing_found(folder, len(images), polarity, polarity_setting, what, out))
    noise = est.background_noise(images, foregrounds)
    edge = est.edge_profile(edges)

    inner = np.concatenate([t["diameter_px"][~t["touches_border"]] for t in tables])
    if inner.size == 0:  # every particle touches the border: their sizes are cut, but they are all there is
        inner = np.concatenate([t["diameter_px"] for t in tables])
    fits, chosen = est.fit_sizes(inner, seed=int(cfg.get("seed", 0)))
    counts = np.concatenate(counts)
    touching = float(np.mean(np.concatenate([t["touches_other"] for t in tables])))
    ce_values = [c for c in ce if c is not None]
    ce_median = float(np.median(ce_values)) if ce_values else None
    ratios = np.concatenate([t["axis_ratio"][~t["touches_border"]] for t in tables])
    axis_ratio = float(np.median(ratios[np.isfinite(ratios)]))
    pixel_sizes = [est.pixel_size_nm(p) for p in paths]
    known = [s for s, _ in pixel_sizes if s is not None]

    result = {
        "name": name,
        "data": {
            "dir": str(folder.resolve()),
            "crop_rows": list(crop) if isinstance(crop, tuple) else crop,
            "split": str(split_path.resolve()) if split_path else None,
            "images": len(images),
            "ids": [p.stem for p in paths],
            "shape": list(images[0].shape),
        },
        "polarity": {"value": polarity, "setting": polarity_setting, **(estimate.as_dict() if estimate else {})},
        "segmentation": {
            "scale_px": params.scale,
            "scale_estimate": scale.as_dict() if scale else None,
            "setting": {k: v for k, v in setting.as_dict().items() if v != SegmentParams().as_dict()[k]},
            "separability_median": round(float(np.median(separabilities)), 4),
            # images whose outlines grew out to the particles' edges, and the foreground added (median over those)
            "outlines_grown": {
                "images": sum(g > 0 for g in grown),
                "foreground_added_median": round(float(np.median([g for g in grown if g > 0] or [0.0])), 4),
            },
            "params": params.as_dict(),
            "particles": int(sum(len(t["diameter_px"]) for t in tables)),
            "particles_not_touching_border": int(inner.size),
        },
        "background": noise.as_dict(),
        "sizes": {
            "median_diameter_px": round(float(np.median(inner)), 3),
            "mean_diameter_px": round(float(inner.mean()), 3),
            "quantiles_px": {q: round(float(np.quantile(inner, float(q))), 3) for q in ("0.1", "0.25", "0.75", "0.9")},
            "fits": [f.as_dict() for f in fits],
            "chosen": chosen.kind,
            "criterion": "lowest BIC = k ln(n) - 2 ln(L), likelihoods in diameter space",
        },
        "particles_per_patch": {
            "definition": f"segments (any, border-touching included) whose centroid lies inside a "
            f"{patch} px window; windows on a grid of stride {patch // 2} px",
            "patch_size": patch,
            "windows": int(counts.size),
            "mean": round(float(counts.mean()), 3),
            "median": float(np.median(counts)),
            "p10": float(np.quantile(counts, 0.1)),
            "p90": float(np.quantile(counts, 0.9)),
            # The windows training keeps (data.min_particles: 3 by default): the scene's range.
            "with_3_or_more": _quantiles(counts[counts >= 3]),
        },
        "agglomeration": {
            "touching_fraction": round(touching, 4),
            "clark_evans_median": round(ce_median, 4) if ce_median is not None else None,
            "placement": est.placement_kind(touching, ce_median),
        },
        "shape": {"axis_ratio_median": round(axis_ratio, 4), "mesh_kind": est.mesh_kind(axis_ratio)},
        "edge": edge.as_dict() if edge is not None else None,
        "pixel_size": {
            "nm_per_px": round(float(np.median(known)), 5) if known else None,
            "source": pixel_sizes[0][1] if known else "unknown",
            "images_with_size": len(known),
        },
    }
    result["out"] = str(out.resolve())
    _write_figures(out, images, labels_kept, inner, fits, chosen, noise, foregrounds, counts, polarity)
    if scale is not None:
        _scale_figure(out, scale.as_dict())
    _edge_figure(out, edge)
    parent, yaml_text = material_yaml(result, fits, chosen)
    fringe = fringe_settings(result["edge"])[0] if parent_renders_fringe(parent) else None
    result["material"] = {
        "parent": parent,
        "config": str(conf_path.resolve()),
        "data": data_settings(result)[0],
        "fringe": fringe,  # material.imaging.fringe as written (None: the material renders no fringe)
    }
    write_json(out / "profile.json", result)
    write_bytes(out / "report.md", report_markdown(result).encode())
    write_bytes(conf_path, yaml_text.encode())
    log.info("wrote %s and %s (parent material %s)", out / "profile.json", conf_path, parent)
    return result


def _segment_setting(cfg: DictConfig) -> SegmentParams:
    """data.segment: SegmentParams keys to set by hand (null or {}: all from the particle scale)."""
    segment = cfg.data.get("segment")
    return SegmentParams.from_config(OmegaConf.to_container(segment) if isinstance(segment, DictConfig) else segment)


def _nothing_found(folder: Path, n: int, polarity: str, setting: str, what: str, out: Path) -> str:
    other = "dark" if polarity == "bright" else "bright"
    return (
        f"profile: data.dir={folder}: no particles found in {n} image(s) ({polarity} particles, "
        f"{'detected' if setting == 'auto' else 'set'}): {what}. The images, as the profile read them, are in "
        f"{out / 'particles.png'}. If they show particles: set their diameter with data.segment.scale=PX (seen in "
        f"the figure), data.polarity={other} if they are {other}er than their background, data.crop_rows if a bar "
        "hides them; data.segment.min_separability lower (e.g. 0.6) for faint particles"
    )


def _write_failure_figure(out: Path, images, polarity: str, labels) -> None:
    """particles.png even when nothing was found: the images (with any segments) the user is asked to look at."""
    labels = labels or [None] * min(4, len(images))
    _outline_figure(out, images, [lab if lab is not None else np.zeros(im.shape, np.int32) for im, lab in
                                  zip(images, labels)][:4], polarity)  # fmt: skip


def _quantiles(counts: np.ndarray) -> dict:
    if counts.size == 0:
        return {"windows": 0, "p10": None, "p90": None}
    return {"windows": int(counts.size), "p10": float(np.quantile(counts, 0.1)), "p90": float(np.quantile(counts, 0.9))}


# --- the material config ----------------------------------------------------------------------------------

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


def data_settings(result: dict) -> tuple[dict, dict]:
    """(data keys, notes): the segmentation the profile validated (data.segment, so that training mines with the
    same lengths) and data.min_particles when too few windows hold the default 3 particles (large particles)."""
    seg, counts = result["segmentation"], result["particles_per_patch"]
    given = seg["setting"]
    # the lengths (from the scale or given), and any other key given by hand (neck_depth, min_separability, ..)
    data = {"segment": {k: v for k, v in seg["params"].items() if k in SEGMENT_KEYS or k in given}}
    estimate = seg["scale_estimate"]
    log_scale = (
        "no LoG blob stood out (particles fill the image), a diameter searched from 8 px up,"
        if estimate is None or estimate["diameter_px"] is None
        else f"LoG blob scale {estimate['diameter_px']} px,"
    )
    if "scale" in given:
        how = "set by hand (data.segment)"
    elif estimate.get("plateau"):
        size = result["sizes"]["median_diameter_px"]
        how = (
            f"measured: {log_scale} no scale agreed with its segments' size and separated enough; from "
            f"{estimate['refined_px']} px up the segments keep one size ({size:.1f} px) over an octave and more: "
            "small particles that separate from a noisy film only when smoothed more than their size asks (the "
            "scale sets the smoothing; the sizes are the segments')"
        )
    else:
        how = f"measured: {log_scale} refined to the segments' own median ({estimate['refined_px']} px)"
    notes = {
        "data.segment.scale": f"particle diameter {seg['scale_px']} px, {how}",
        "data.segment (sigma, min_distance, min_area, max_area, background)": "from the scale unless set by hand"
        + (f" ({', '.join(sorted(given))} given)" if given else "")
        + f"; Otsu separability {seg['separability_median']:.2f} (particles segmented: {seg['particles']})",
    }
    notes["data.segment.neck_depth"] = _neck_note(seg["params"]["neck_depth"], "neck_depth" in given, estimate)
    lowered = seg["params"]["min_separability"]
    if lowered != CALIBRATION.min_separability and "min_separability" not in given:
        data["segment"]["min_separability"] = lowered
        notes["data.segment.min_separability"] = (
            f"{lowered} (default {CALIBRATION.min_separability}): the particles' scale separates less than a "
            "finer one, but its segments are far more alike in size (a dense packing of textured particles: narrow "
            "gaps, texture cut into specks of every size at the finer scale); to decide, set data.segment.scale "
            "and data.segment.min_separability together"
        )
    notes["data.segment.grow_outlines"] = _outline_note(seg, result["data"]["images"])
    enough = counts["with_3_or_more"]["windows"] / max(1, counts["windows"])
    if enough < MIN_WINDOW_SHARE:
        data["min_particles"] = max(1, min(3, int(counts["median"])))
        notes["data.min_particles"] = (
            f"{data['min_particles']}: only {100 * enough:.0f} % of the {counts['patch_size']} px windows hold 3 or "
            f"more particles (median {counts['median']:g})"
        )
    return data, notes


WHY_SEGMENT = {"scale": "measured", "neck_depth": "chosen by the segment sizes (note below)"}
SEGMENT_KEYS = ("scale", "sigma", "min_distance", "min_area", "max_area", "background", "neck_depth")
MIN_WINDOW_SHARE = 0.2  # below this share of windows with >= 3 particles, training mines windows with fewer


def material_settings(result: dict, fits: list, chosen) -> tuple[str, str, dict, dict, dict]:
    """(parent, why, material, size, notes): what the profile measured, as the keys of a material inheriting the
    closest paper material (`choose_parent`), the size group's parameters for a bimodal fit (else {}), and per key
    why it was set."""
    polarity = result["polarity"]["value"]
    sizes, counts = result["sizes"], result["particles_per_patch"]
    kind = result["shape"]["mesh_kind"]
    parent, why = choose_parent(polarity, kind, sizes["median_diameter_px"])
    by_kind = {f.kind: f for f in fits}
    if chosen.kind == "normal":
        size_px, spread = chosen.params["mean"], chosen.params["std"] / chosen.params["mean"]
        spread_note = "std / mean of the normal fit"
    else:
        lognormal = by_kind["lognormal"].params
        size_px, spread = lognormal["median"], lognormal["sigma"]
        spread_note = "sigma of log(diameter), lognormal fit"
    # A material's sizes are largest extents (a mesh's scale); the profile measures equivalent diameters of
    # projected areas: ~0.9 x the largest extent for the TiO2 particles (tio2_sem: masks 26.5 px, extent 30 px).
    size_px *= EXTENT_PER_DIAMETER
    kept = counts["with_3_or_more"] if counts["with_3_or_more"]["windows"] else counts
    n_max = max(1, int(math.ceil(kept["p90"])))
    n_min = max(1, min(n_max, int(math.floor(kept["p10"]))))
    pol_note = "detected" if result["polarity"]["setting"] == "auto" else "set on the command line"
    material = {
        "name": result["name"],
        "polarity": polarity,
        "particle_size_px": round(float(size_px), 1),
        "size_spread": round(float(spread), 3),
        "n_particles": n_max,
        "n_particles_min": n_min,
        "meshes": {"kind": kind},
    }
    notes = {
        "polarity": pol_note,
        "particle_size_px": f"median equivalent diameter of the segmented particles x {EXTENT_PER_DIAMETER} (a "
        "material's size is a particle's largest extent)",
        "size_spread": spread_note,
        "n_particles": f"p90 of particles per {counts['patch_size']} px patch over the patches with >= 3 (those "
        f"training keeps; mean over all patches {counts['mean']:.1f})",
        "n_particles_min": "p10 over the same patches; a constellation draws n_particles_min..n_particles",
        "meshes.kind": f"median major/minor axis ratio {result['shape']['axis_ratio_median']:.2f}",
    }
    background = result["background"]
    if parent_renders_without_sampling_noise(parent):
        # Such a render has no Monte Carlo grain: the image's noise is the detector's, which the background shows,
        # so it bounds the learned noise (tio2_tsem: 0.018 measured; wider limits start far too grainy).
        material["noise_grain_px"] = round(float(background["grain_px"]), 2)
        material["noise_sigma"] = {
            "min": 0.001,
            "max": round(max(NOISE_LIMIT_FLOOR, NOISE_LIMIT_FACTOR * background["noise_sigma"]), 4),
        }
        notes["noise_grain_px"] = (
            f"lag-1 autocorrelation {background['lag1_autocorrelation']:.3f} of the background's high-pass residual"
        )
        notes["noise_sigma.max"] = f"{NOISE_LIMIT_FACTOR} x the background's noise sigma"
    stage = stage_limits(parent, background["background_grey"])
    if stage is not None:
        material["imaging"] = {"stage_bsdf": {"base_color": stage[0]}}
        notes["imaging.stage_bsdf.base_color"] = stage[1]
    if parent_renders_fringe(parent):
        fringe, why_fringe = fringe_settings(result.get("edge"))
        if fringe is not None:  # only a measured fringe: without one the material renders none
            material["imaging"] = {"fringe": fringe}
            notes["imaging.fringe"] = why_fringe
    size = {}
    if chosen.kind == "bimodal":
        p = chosen.params
        m1, s1 = (EXTENT_PER_DIAMETER * v for v in est.lognormal_to_normal(p["median1"], p["sigma1"]))
        m2, s2 = (EXTENT_PER_DIAMETER * v for v in est.lognormal_to_normal(p["median2"], p["sigma2"]))
        size = {
            k: round(float(v), 3)
            for k, v in zip(("mean1", "std1", "mean2", "std2", "weight1"), (m1, s1, m2, s2, p["weight1"]))
        }
        notes["size"] = f"the two lognormal components as normals (mean, std, px) x {EXTENT_PER_DIAMETER}"
    return parent, why, material, size, notes


@functools.cache
def parent_material(parent: str) -> dict:
    """The paper material ``parent`` as plain values (composed once per process; callers do not modify it)."""
    from drgan.configs import compose

    return OmegaConf.to_container(compose([f"material={parent}"], config_name="render").material, resolve=True)


def parent_renders_fringe(parent: str) -> bool:
    """Whether the parent material's imaging takes an edge fringe (``material.imaging.fringe``: transmission)."""
    from drgan.scene.config import typed_material

    return typed_material(parent_material(parent)).imaging.renders_fringe


FRINGE_LIMIT_FACTOR = 2.0  # a measured fringe's amplitude is learned within 0..2 x the fitted amplitude


def fringe_settings(edge: dict | None) -> tuple[dict | None, str]:
    """(``material.imaging.fringe`` or None, why): set only when the edge profile shows a ring (the rule of
    `drgan.data.profile.find_ring`); its amplitude learned between 0 (no fringe) and FRINGE_LIMIT_FACTOR x the
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
        saturated = sum(share is not None and share > est.MAX_SATURATED for share in edge["saturated_share"])
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

    from drgan.configs import compose
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
    stage at most ~0.15 grey; SEM images with a mid-grey stage (EMPS cej: 0.43) need a larger base colour, which the
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


def parent_renders_without_sampling_noise(parent: str) -> bool:
    """Whether the parent material's scene renders without Monte Carlo grain (its imaging config says so)."""
    from drgan.scene.config import typed_material

    return typed_material(parent_material(parent)).imaging.noiseless


def material_yaml(result: dict, fits: list, chosen) -> tuple[str, str]:
    """(parent name, the text of drgan_conf/material/NAME.yaml): the measured keys, checked against the typed
    material (`drgan.scene.config.typed_material`, merged over the parent) and dumped, with why each was set."""
    from drgan.scene.config import typed_material

    parent, why, material, size, notes = material_settings(result, fits, chosen)
    typed_material(
        OmegaConf.merge(parent_material(parent), material)
    )  # a value the schema refuses fails here, not in training
    agg, data = result["agglomeration"], result["data"]
    notes["size group"] = f"{chosen.kind}: lowest BIC of normal / lognormal / bimodal"
    notes["placement group"] = (
        f"{agg['placement']}: touching fraction {agg['touching_fraction']:.2f}, Clark-Evans {agg['clark_evans_median']}"
    )
    body = {"material": material}
    if size:
        body["size"] = size
    segmentation, data_notes = data_settings(result)
    notes.update(data_notes)
    body["data"] = {
        "dir": data["dir"],
        "crop_rows": data["crop_rows"],
        "split": data["split"],
        "polarity": material["polarity"],
        **segmentation,
    }
    header = [
        "# @package _global_",
        f"# Written by `python -m drgan.profile` from {data['images']} image(s) of {data['dir']}",
        f"# (report: {result['out']}/report.md).",
        f"# Parent: {parent} ({why}); everything not set here comes from it, unmeasured.",
        "# Measured:",
        *(f"#   {key}: {note}" for key, note in notes.items()),
        f"#   for reference: background grey {result['background']['background_grey']:.3f}, noise sigma "
        f"{result['background']['noise_sigma']:.4f}",
        *(
            [f"#   edge fringe: {fringe_settings(result.get('edge'))[1]}; the material renders none"]
            if parent_renders_fringe(parent) and "imaging" not in material
            else []
        ),
        "defaults:",
        f"  - {parent}",
        f"  - override /size: {chosen.kind}",
        f"  - override /placement: {agg['placement']}",
    ]
    return parent, "\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(body))


# --- report and figures -----------------------------------------------------------------------------------


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


def _outline_note(seg: dict, images: int) -> str:
    """What the outlines' growth to the particles' edges did (`drgan.data.classical.grow_to_edges`)."""
    if not seg["params"].get("grow_outlines", True):
        return "false (set by hand): Otsu's outlines"
    grown = seg.get("outlines_grown") or {"images": 0}
    if not grown["images"]:
        return f"true: on none of the {images} images did the strongest edges lie below Otsu's threshold"
    return (
        f"true: the outlines grew out to the particles' strongest edges, below Otsu's threshold, on {grown['images']} "
        f"of {images} images (foreground +{100 * grown['foreground_added_median']:.0f} %, median); false keeps Otsu's"
    )


def report_markdown(r: dict) -> str:
    b, s, c, a = r["background"], r["sizes"], r["particles_per_patch"], r["agglomeration"]
    seg = r["segmentation"]
    fits = "\n".join(
        f"| {f['kind']}{' (chosen)' if f['kind'] == s['chosen'] else ''} | "
        + ", ".join(f"{k} {v:g}" for k, v in f["params"].items())
        + f" | {f['log_likelihood']:.1f} | {f['bic']:.1f} |"
        for f in s["fits"]
    )
    px = r["pixel_size"]
    data, data_notes = data_settings(r)  # the table shows the keys the material carries
    seg_table = "| key | value | why |\n|---|---|---|\n" + "\n".join(
        f"| data.segment.{k} | {v} | {'set by hand' if k in seg['setting'] else WHY_SEGMENT.get(k, 'from the scale')} |"
        for k, v in data["segment"].items()
    )
    seg_table += "\n\n" + "\n".join(f"- `{k}`: {v}" for k, v in data_notes.items())
    return (
        _report_head(r, b, s, c, a, seg, px, seg_table, fits)
        + edge_markdown(r.get("edge"), r["material"])
        + "\nFigures: `sizes.png`, `scale_search.png`, `particles.png` (real images: keep them out of repositories), "
        "`background_noise.png`, `edge_profile.png`.\n"
    )


def edge_markdown(edge: dict | None, material: dict) -> str:
    """The report's section on the mean particle edge: the ring the rule found, the fit, what the material got."""
    written = material.get("fringe")
    parent_takes = parent_renders_fringe(material["parent"])
    if written is not None:
        verdict = f"written: `material.imaging.fringe: {written}`"
    elif parent_takes:
        verdict = "none written: the material renders no fringe"
    else:
        verdict = f"not written: the parent material `{material['parent']}` renders no fringe (transmission only)"
    head = "\n## Mean particle edge (edge_profile.png)\n\n"
    if edge is None:
        return head + f"Too few isolated particles for an edge profile. Fringe: {verdict}.\n"
    ring, fit = edge["ring"], edge["fringe"]
    kinds = {"opposite": "opposite to the particles' grey (overshoot)", "like": "like the particles (bump)"}
    rows = [
        ("isolated particles used (not touching the border or another segment)", edge["particles"]),
        ("particle contrast (interior minus background grey)", f"{edge['contrast']:+.4f}"),
        ("ring outside the edge", kinds.get(ring["kind"], "none")),
        (
            "its height (particle contrast; > 0 opposite grey) / standard error / distance (px)",
            f"{ring['height']:+.4f} / {ring['height_se']:.4f} / {ring['distance_px']:.2f}",
        ),
    ]
    if fit is not None:
        rows += [
            (
                "fitted fringe amplitude / width w (px) / edge blur (px)",
                f"{fit['amplitude']:+.4f} / {fit['width_px']:.2f} / {fit['edge_blur_px']:.2f}",
            ),
            ("fit: reduced chi^2", f"{fit['reduced_chi2']:.2f}"),
        ]
    table = "| quantity | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
    bins = "| distance (px) | profile | standard error | particles |\n|---|---|---|---|\n" + "\n".join(
        f"| {d:.2f} | {p:.4f} | {e:.4f} | {n} |"
        for d, p, e, n in zip(edge["distance_px"], edge["profile"], edge["standard_error"], edge["particles_per_bin"])
        if d is not None and p is not None and e is not None
    )
    return f"""{head}Grey against signed distance to the segmented edge (< 0 inside), 0 = each particle's background \
({est.EDGE_OUTSIDE_PX}-{est.EDGE_BACKGROUND_PX} px outside), 1 = its interior ({est.EDGE_INTERIOR_PX}-\
{est.EDGE_INSIDE_PX} px inside). Rule: {edge["rule"]}. Fringe: {verdict}.

{table}

{bins}
"""


def _report_head(r, b, s, c, a, seg, px, seg_table, fits) -> str:
    return f"""# Profile: {r["name"]}

{r["data"]["images"]} image(s) of `{r["data"]["dir"]}` (crop_rows {r["data"]["crop_rows"]}, split {r["data"]["split"]}).
Material config: `{r["material"]["config"]}` (parent `{r["material"]["parent"]}`).

| quantity | value |
|---|---|
| polarity | {r["polarity"]["value"]} ({r["polarity"]["setting"]}; confidence {r["polarity"].get("confidence", "-")}) |
| background grey (median of background pixels) | {b["background_grey"]:.4f} |
| noise sigma (MAD of the high-pass residual, corrected) | {b["noise_sigma"]:.4f} |
| lag-1 autocorrelation of the residual | {b["lag1_autocorrelation"]:.3f} |
| grain (Gaussian stddev, px) | {b["grain_px"]:.2f} |
| particles segmented / not touching the border | {seg["particles"]} / {seg["particles_not_touching_border"]} |
| median / mean equivalent diameter (px) | {s["median_diameter_px"]:.2f} / {s["mean_diameter_px"]:.2f} |
| particles per {c["patch_size"]} px patch: mean / median (p10-p90) | {c["mean"]:.2f} / {c["median"]:g} \
({c["p10"]:g}-{c["p90"]:g}) |
| touching fraction / Clark-Evans ratio | {a["touching_fraction"]:.3f} / {a["clark_evans_median"]} \
-> placement {a["placement"]} |
| median axis ratio | {r["shape"]["axis_ratio_median"]:.3f} -> meshes {r["shape"]["mesh_kind"]} |
| pixel size | {px["nm_per_px"]} nm ({px["source"]}) |

Particles per patch: {c["definition"]}.
## Segmentation (drgan.data.classical; written to the material's `data` keys, so training mines alike)

{seg_table}

## Diameter fits ({s["criterion"]})

| fit | parameters (px; sigma of log d) | log L | BIC |
|---|---|---|---|
{fits}
"""


def _scale_figure(out: Path, search: dict) -> None:
    """scale_search.png: the segments' median diameter at each scale segmented, per neck depth, against the diagonal
    where a segmentation agrees with its own scale (band: Calibration.consistent); the fixed points found, marked by how many
    scales segment to their size (the basin), and the one chosen (`drgan.data.classical.search_scale`)."""
    grid = np.array([[s, d, np.nan if m is None else m] for s, d, m, _ in search["grid"]], dtype=float)
    fixed = [Fixed.from_list(c) for c in search["candidates"]]

    def plot(plt):
        fig, ax = plt.subplots(figsize=(6.5, 5))
        lo, hi = np.nanmin(grid[:, :1]) / 1.5, np.nanmax(grid[:, [0, 2]]) * 1.5
        x = np.geomspace(lo, hi, 50)
        ax.fill_between(
            x,
            x * math.exp(-CALIBRATION.consistent),
            x * math.exp(CALIBRATION.consistent),
            color="0.9",
            label="agrees with its scale",
        )
        ax.plot(x, x, color="0.6", lw=0.8)
        for depth, colour in ((0.0, "C0"), (CALIBRATION.neck_depth, "C1")):
            row = grid[grid[:, 1] == depth]
            row = row[np.argsort(row[:, 0])]
            what = "every maximum seeds" if depth == 0 else f"seeds at necks ({depth})"
            ax.plot(row[:, 0], row[:, 2], "o-", ms=3, color=colour, label=f"segments' median, {what}")
            for f in (f for f in fixed if f.depth == depth):
                ax.scatter(f.scale, f.median, s=20 + 15 * f.basin, facecolors="none", edgecolors=colour)
                ax.annotate(str(f.basin), (f.scale, f.median), textcoords="offset points", xytext=(6, -10),
                            fontsize=7, color=colour)  # fmt: skip
        if search.get("refined_px"):
            ax.axvline(search["refined_px"], color="k", ls="--", lw=1, label=f"chosen {search['refined_px']} px")
        ax.set(xscale="log", yscale="log", xlim=(lo, hi), ylim=(lo, hi), xlabel="scale segmented with (px)",
               ylabel="segments' median diameter (px)",
               title="particle scale search (circles: fixed points, number: scales holding their size)")  # fmt: skip
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7, loc="upper left")
        return fig

    write_bytes(out / "scale_search.png", figure_png(plot))


def _write_figures(out, images, labels, diameters, fits, chosen, noise, foregrounds, counts, polarity) -> None:
    def sizes(plt):
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.hist(diameters, bins=40, density=True, color="0.8", label=f"{diameters.size} particles")
        x = np.linspace(max(diameters.min() * 0.8, 0.1), diameters.max() * 1.1, 400)
        for f in fits:
            best = f.kind == chosen.kind
            ax.plot(x, f.pdf(x), lw=3 if best else 1.2, label=f"{f.kind} (BIC {f.bic:.0f}){' chosen' if best else ''}")
        ax.set_xlabel("equivalent diameter (px)")
        ax.set_ylabel("density")
        ax.legend()
        return fig

    def background(plt):
        fig, axes = plt.subplots(1, 3, figsize=(14, 3.5))
        grey = np.concatenate([np.asarray(im)[est.background_mask(fg)] for im, fg in zip(images[:8], foregrounds[:8])])
        axes[0].hist(grey, bins=100, color="0.5")
        axes[0].axvline(noise.background_grey, color="r", label=f"median {noise.background_grey:.3f}")
        axes[0].set_xlabel("background grey")
        axes[0].legend()
        residual = np.concatenate(
            [est.highpass(im)[est.background_mask(fg)] for im, fg in zip(images[:8], foregrounds[:8])]
        )
        lim = 6 * max(noise.residual_sigma, 1e-6)
        axes[1].hist(residual, bins=100, range=(-lim, lim), density=True, color="0.5")
        x = np.linspace(-lim, lim, 200)
        gauss = np.exp(-0.5 * (x / noise.residual_sigma) ** 2) / (noise.residual_sigma * math.sqrt(2 * math.pi))
        axes[1].plot(x, gauss, "r", label=f"MAD sigma {noise.residual_sigma:.4f}")
        axes[1].set_xlabel(
            f"high-pass residual (lag-1 r {noise.lag1_autocorrelation:.2f}, grain {noise.grain_px:.2f} px)"
        )
        axes[1].legend()
        axes[2].hist(counts, bins=np.arange(counts.max() + 2) - 0.5, color="0.5")
        axes[2].set_xlabel("particles per patch (centroid inside)")
        return fig

    write_bytes(out / "sizes.png", figure_png(sizes))
    _outline_figure(out, images, labels, polarity)
    write_bytes(out / "background_noise.png", figure_png(background))


def _edge_figure(out: Path, edge) -> None:
    """edge_profile.png: the mean edge profile with its errors, the fitted edge and fringe, and the ring found."""

    def plot(plt):
        fig, ax = plt.subplots(figsize=(7, 4))
        if edge is None:
            ax.text(0.5, 0.5, "too few isolated particles for an edge profile", ha="center", transform=ax.transAxes)
            return fig
        d, p, e, used = edge.distance_px, edge.profile, edge.standard_error, edge.usable
        ax.errorbar(d[used], p[used], yerr=2 * e[used], fmt="o", color="k", ms=4, label="mean edge (2 standard errors)")
        skipped = ~used & np.isfinite(p)
        if skipped.any():
            ax.plot(d[skipped], p[skipped], "o", mfc="none", color="0.5", label="not used (saturated or few particles)")
        if edge.fringe is not None:
            f = edge.fringe
            x = np.linspace(d[np.isfinite(d)].min(), d[np.isfinite(d)].max(), 300)
            args = (f.contrast_scale, f.interior_slope, f.edge_offset_px, f.edge_blur_px)
            ax.plot(x, est.edge_model(x, *args, f.amplitude, f.width_px, edge.radius_px), "r",
                    label=f"fit: fringe amplitude {f.amplitude:+.3f}, width {f.width_px:.2f} px")  # fmt: skip
            ax.plot(x, est.edge_model(x, *args, 0.0, f.width_px, edge.radius_px), "r:", lw=1, label="fit, no fringe")
        if edge.ring.kind != "none":
            ax.plot([edge.ring.distance_px], [-edge.ring.height], "v", color="tab:blue", ms=10,
                    label=f"ring ({edge.ring.kind}): {edge.ring.height:+.3f}")  # fmt: skip
        ax.axhline(0, color="0.6", lw=0.8)
        ax.axhline(1, color="0.6", lw=0.8, ls="--")
        ax.axvline(0, color="0.6", lw=0.8)
        ax.set_xlabel("signed distance to the segmented edge (px; < 0 inside)")
        ax.set_ylabel("grey, particle contrast (0 background, 1 interior)")
        ring = {"opposite": "a ring of the opposite grey", "like": "a ring like the particles"}.get(edge.ring.kind)
        ax.set_title(f"mean edge of {edge.particles} isolated particles: {ring or 'no ring'}")
        ax.legend(fontsize=8)
        return fig

    write_bytes(out / "edge_profile.png", figure_png(plot))


def _outline_figure(out: Path, images, labels, polarity: str) -> None:
    from skimage.segmentation import find_boundaries

    def outlines(plt):
        shown = [(im, lab) for im, lab in zip(images, labels) if lab is not None][:4]
        fig, axes = plt.subplots(1, len(shown), figsize=(5 * len(shown), 4), squeeze=False)
        for ax, (im, lab) in zip(axes[0], shown):
            rgb = np.repeat(im[..., None], 3, axis=2)
            rgb[find_boundaries(lab, mode="outer")] = (1.0, 0.2, 0.1)
            ax.imshow(rgb)
            ax.set_title(f"{int(lab.max() and len(np.unique(lab)) - 1)} segments ({polarity})")
            ax.axis("off")
        return fig

    write_bytes(out / "particles.png", figure_png(outlines))


@stage_main("conf/gan", "profile")
def main(cfg: DictConfig):
    OmegaConf.resolve(cfg)
    profile(cfg)


if __name__ == "__main__":
    start(main)
