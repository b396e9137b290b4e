"""`python -m drgan.profile data.dir=DIR name=NAME`: profile unannotated particle images, write a material config.

Reads every (train) image, detects the polarity, segments the particles classically (drgan.data.measurements), and
measures background grey, noise sigma and grain, the mean particle edge (and a defocus fringe on it), the diameter
distribution (normal / lognormal / two-lognormal mixture, chosen by BIC), particles per patch, agglomeration,
elongation and the pixel size. Writes, in `out` (default runs/profile/NAME): profile.json (every number),
report.md, sizes.png, scale_search.png (how the particle scale was found), particles.png (real images with the
detected outlines: keep them out of the repository), background_noise.png, edge_profile.png
(drgan.profiling.figures); and ./drgan_conf/material/NAME.yaml, a material inheriting the closest paper material
(drgan.profiling.proposal), ready for `python -m drgan.train material=NAME`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_bytes, write_json
from drgan.core.progress import track
from drgan.core.typed_settings import given, read_settings, setting, typed
from drgan.data import measurements as est
from drgan.data import particle_edge
from drgan.data.annotations import annotation_mask, as_grey
from drgan.data.classical import NoParticles, SegmentParams, resolve_params
from drgan.data.imagej import write_label_tiff
from drgan.data.images import default_split, list_images, read_grey, read_split
from drgan.data.particle_edge import EDGE_BACKGROUND_PX, EDGE_INSIDE_PX, EDGE_INTERIOR_PX, EDGE_OUTSIDE_PX
from drgan.data.patches import STRIDE, particle_boxes, scale_sample
from drgan.data.polarity import check_polarity, resolve_polarity
from drgan.launch.configs import material_name
from drgan.launch.runtime import stage_main, start
from drgan.profiling import figures
from drgan.profiling.proposal import (
    EXTENT_PER_DIAMETER,
    WHY_SEGMENT,
    data_settings,
    fringe_settings,
    material_yaml,
    parent_renders_fringe,
)
from drgan.profiling.result import (
    Agglomeration,
    ImagesRead,
    MaterialProposed,
    PatchCounts,
    PixelSize,
    PolarityFound,
    ProfileResult,
    SegmentationFound,
    ShapeFound,
    SizesFound,
)

log = logging.getLogger(__name__)


# --- settings and images ----------------------------------------------------------------------------------


def _material_name(stage: str, name) -> str:
    """``name``: the material's name (drgan.launch.configs.material_name)."""
    return material_name(stage, name, "the material is written as")


def _crop_rows(stage: str, crop) -> tuple[int, int] | str | None:
    """data.crop_rows: [start, stop) with 0 <= start < stop, auto or null."""
    if isinstance(crop, str) and crop != "auto":
        raise ConfigError(f"{stage}: data.crop_rows={crop!r}: expected [start, stop), auto or null")
    if crop is None or crop == "auto":
        return crop
    crop = list(crop)
    if len(crop) != 2 or not all(isinstance(v, int) for v in crop) or not 0 <= crop[0] < crop[1]:
        raise ConfigError(f"{stage}: data.crop_rows={crop}: expected [start, stop) with 0 <= start < stop")
    return crop[0], crop[1]


@typed
@dataclass(frozen=True)
class ProfileData:
    """The ``data`` keys of conf/gan/profile.yaml: the images and how to read them."""

    dir: Path | None = None
    crop_rows: tuple[int, int] | str | None = setting("auto", check=_crop_rows)
    split: str | None = "auto"  # resolved by `resolve_split`
    polarity: str = setting("auto", check=lambda stage, v: check_polarity(v, "data.polarity", allow_auto=True))
    segment: SegmentParams = setting(SegmentParams(), check=lambda stage, v: SegmentParams.from_config(v))


@typed
@dataclass(frozen=True)
class ProfileSettings:
    """The settings of a profile run: every key of conf/gan/profile.yaml with its type, its default and its check
    (`from_config`, by `drgan.core.typed_settings.read_settings`), resolved before any image is read. The YAML stays the
    user's reference (what each key means); the field defaults are the same values (tests/test_profile.py composes
    profile.yaml and compares). A new key is a field here (its check beside it) and, where users should see it, its
    line in the YAML."""

    name: str = setting(check=_material_name)
    data_dir: Path = setting()  # data.dir
    out: Path = setting()  # figures, profile.json, report.md (the YAML's default: runs/profile/NAME)
    crop_rows: tuple[int, int] | str | None = "auto"  # [start, stop), "auto" (the info bar found) or None
    split: Path | None = None  # the split.json whose train ids are profiled (data.split resolved); None: every image
    polarity: str = "auto"
    segment: SegmentParams = field(default_factory=SegmentParams)  # data.segment keys set by hand
    patch_size: int = setting(256, ge=16, expected="an integer >= 16 px")
    max_images: int | None = setting(None, ge=1, expected="a positive integer or null")
    overwrite: bool = False
    conf_dir: Path = Path("drgan_conf")
    seed: int = 0

    @property
    def conf_path(self) -> Path:
        """Where the material config goes: conf_dir/material/NAME.yaml."""
        return self.conf_dir / "material" / f"{self.name}.yaml"

    @classmethod
    def from_config(cls, cfg: DictConfig) -> ProfileSettings:
        """From the composed profile config; a `ConfigError` naming the key for any value that cannot be right."""
        no_dir = "profile: give data.dir=DIR (a folder of particle images)"
        data = read_settings(ProfileData, given(cfg, "data", no_dir), "profile", prefix="data.")
        if data.dir is None:  # null or empty
            raise ConfigError(no_dir)
        folder = data.dir.expanduser()
        settings = read_settings(
            cls, cfg, "profile", data_dir=folder, crop_rows=data.crop_rows, polarity=data.polarity, segment=data.segment
        )
        if not folder.is_dir():
            raise ConfigError(f"profile: data.dir={folder}: no such folder (expected a folder of images)")
        if settings.conf_path.exists() and not settings.overwrite:
            raise ConfigError(f"profile: {settings.conf_path} exists; choose another name= or set overwrite=true")
        return replace(settings, split=resolve_split(folder, data.split))


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


def profile(settings: ProfileSettings) -> ProfileResult:
    """Profile the images of data.dir; write figures, profile.json, report.md and the material config."""
    s = settings
    paths = select_images(s.data_dir, s.split, s.max_images)
    images = [read_grey(p, s.crop_rows) for p in track(paths, "reading", unit="images")]  # checks crop on every image
    small = [p.name for p, im in zip(paths, images) if min(im.shape) < s.patch_size]
    if small:
        raise DataError(f"profile: image(s) {small[:3]} are smaller than patch_size={s.patch_size} px after cropping")

    polarity, estimate = resolve_polarity(s.polarity, images)
    log.info("polarity: %s (%s)", polarity, "detected" if estimate else "set")
    if estimate is not None:
        _warn_mixed_polarity(estimate, paths)
    params, scale = _particle_scale(s, images, polarity)
    seg = segment_all(s.out, paths, images, params, polarity)
    if not sum(len(t["diameter_px"]) for t in seg.tables):
        _write_failure_figure(s.out, images, polarity, seg.labels_kept)
        what = (
            f"the particle scale {params.scale} px was found, but no segment of plausible area "
            f"({params.min_area}-{params.max_area} px^2) came out of the watershed (settings {params.as_dict()}; Otsu "
            f"separability {max(seg.separabilities):.2f}, needed {params.min_separability})"
        )
        raise DataError(_nothing_found(s.data_dir, len(images), polarity, s.polarity, what, s.out))
    result, fits, chosen, sizes = measure(s, paths, images, polarity, estimate, params, scale, seg)
    return write_profile(s, result, images, seg, sizes, fits, chosen, polarity, scale)


def _particle_scale(s: ProfileSettings, images: list, polarity: str):
    """(segmentation parameters, the scale search) on the images mining searches the scale on (scale_sample); the
    data.segment keys given are kept as given. Where no particle is found: the failure figures, then a DataError."""
    try:
        return resolve_params(scale_sample(images), s.segment, polarity, progress=True)
    except NoParticles as error:
        _write_failure_figure(s.out, images, polarity, None)
        if error.search is not None:
            figures.scale_figure(s.out, error.search.as_dict())
        raise DataError(_nothing_found(s.data_dir, len(images), polarity, s.polarity, error.what, s.out)) from None


@dataclass
class Segmented:
    """What `segment_all` measured per image: particle tables, foregrounds, the first four label images (figures),
    shapes, Clark-Evans ratios, Otsu separabilities, edge samples, foreground grown to the edges, edge blurs and the
    particles' boxes."""

    tables: list = field(default_factory=list)
    foregrounds: list = field(default_factory=list)
    labels_kept: list = field(default_factory=list)
    shapes: list = field(default_factory=list)
    ce: list = field(default_factory=list)
    separabilities: list = field(default_factory=list)
    edges: list = field(default_factory=list)
    grown: list = field(default_factory=list)
    blurs: list = field(default_factory=list)
    boxes: list = field(default_factory=list)


def segment_all(out: Path, paths: list, images: list, params: SegmentParams, polarity: str) -> Segmented:
    """Every image segmented classically with ``params``: its labels written (labels/ID.tif: the classical outlines
    for Fiji and napari, and the reference drgan.segment's agreement check compares a trained segmenter with,
    drgan.segmenters.agreement) and measured."""
    seg = Segmented()
    for path, image in track(list(zip(paths, images)), "segmenting", unit="images"):
        labels, foreground, separability, added = est.segment_image(image, params, polarity)
        write_label_tiff(out / "labels" / f"{path.stem}.tif", labels, est.pixel_size_nm(path)[0])
        table = est.particle_table(labels)
        seg.tables.append(table)
        seg.foregrounds.append(foreground)
        seg.separabilities.append(separability)
        seg.grown.append(added)
        seg.labels_kept.append(labels if len(seg.labels_kept) < 4 else None)
        # The edge profile leaves out particles beside annotations (a scale bar may hide a neighbour).
        exclude = annotation_mask(as_grey(image)) if params.annotations else None
        seg.edges.append(particle_edge.edge_samples(image, labels, foreground, exclude))
        seg.blurs.append(est.edge_blur(image, foreground, exclude))
        seg.shapes.append(labels.shape)
        seg.boxes.append(particle_boxes(labels, params))
        seg.ce.append(est.clark_evans(table["row"], table["col"], labels.size))
    return seg


def measure(s: ProfileSettings, paths, images, polarity, estimate, params, scale, seg: Segmented):
    """(the ProfileResult without its material, the size fits, the chosen fit, the half-contrast sizes and the
    per-window counts and noise for the figures): everything the profile reports, from `segment_all`'s
    measurements."""
    noise = est.background_noise(images, seg.foregrounds)
    edge = particle_edge.edge_profile(seg.edges)
    tables, shapes = seg.tables, seg.shapes
    segmented = np.concatenate([t["diameter_px"][~t["touches_border"]] for t in tables])
    if segmented.size == 0:  # every particle touches the border: their sizes are cut, but they are all there is
        segmented = np.concatenate([t["diameter_px"] for t in tables])
    # Sizes at half contrast, where the rendered masks (and annotations) put a particle's boundary: the scenes a GAN
    # draws from this distribution then hold particles of the real ones' size, not of the classical outlines'.
    shift = particle_edge.outline_shift(edge)
    inner = np.maximum(segmented + 2.0 * shift, 1.0)
    fits, chosen = est.fit_sizes(inner, seed=s.seed)
    # Training windows wide enough for the particles (large ones: wider than the render, area-averaged to it)
    patch = s.patch_size
    window = est.view_window(EXTENT_PER_DIAMETER * float(np.median(inner)), patch, min(min(x) for x in shapes))
    if window != patch:
        log.info(
            "particles of %.0f px median diameter: training windows of %d real px, rendered at %d px (%.2g x)",
            np.median(inner), window, patch, patch / window,
        )  # fmt: skip
    counts = np.concatenate([est.patch_counts(t["row"], t["col"], sh, window) for t, sh in zip(tables, shapes)])
    whole = np.concatenate([est.whole_particle_counts(b, sh, window) for b, sh in zip(seg.boxes, shapes)])
    touching = float(np.mean(np.concatenate([t["touches_other"] for t in tables])))
    ce_values = [c for c in seg.ce if c is not None]
    ce_median = float(np.median(ce_values)) if ce_values else None
    ratios = np.concatenate([t["axis_ratio"][~t["touches_border"]] for t in tables])
    axis_ratio = float(np.median(ratios[np.isfinite(ratios)]))
    pixel_sizes = [est.pixel_size_nm(p) for p in paths]
    known = [size for size, _ in pixel_sizes if size is not None]
    folder, crop, split_path = s.data_dir, s.crop_rows, s.split
    result = ProfileResult(
        name=s.name,
        data=ImagesRead(
            dir=str(folder.resolve()),
            crop_rows=list(crop) if isinstance(crop, tuple) else crop,
            split=str(split_path.resolve()) if split_path else None,
            images=len(images),
            ids=[p.stem for p in paths],
            shape=list(images[0].shape),
        ),
        polarity=PolarityFound(polarity, s.polarity, estimate.as_dict() if estimate else {}),
        segmentation=_segmentation_found(s, params, scale, seg, inner.size),
        background=type(noise)(**noise.as_dict()),  # as recorded: what the report and the material read
        sizes=SizesFound(
            median_diameter_px=round(float(np.median(inner)), 3),
            mean_diameter_px=round(float(inner.mean()), 3),
            quantiles_px={q: round(float(np.quantile(inner, float(q))), 3) for q in ("0.1", "0.25", "0.75", "0.9")},
            fits=[f.as_dict() for f in fits],
            chosen=chosen.kind,
            criterion="lowest BIC = k ln(n) - 2 ln(L), likelihoods in diameter space",
            outline_shift_px=round(shift, 3),
            segmented_median_diameter_px=round(float(np.median(segmented)), 3),
        ),
        particles_per_patch=_patch_counts(window, patch, counts, whole),
        agglomeration=Agglomeration(
            touching_fraction=round(touching, 4),
            clark_evans_median=round(ce_median, 4) if ce_median is not None else None,
            placement=est.placement_kind(touching, ce_median),
        ),
        shape=ShapeFound(axis_ratio_median=round(axis_ratio, 4), mesh_kind=est.mesh_kind(axis_ratio)),
        edge=edge.as_dict() if edge is not None else None,
        pixel_size=PixelSize(
            nm_per_px=round(float(np.median(known)), 5) if known else None,
            source=pixel_sizes[0][1] if known else "unknown",
            images_with_size=len(known),
        ),
        out=str(s.out.resolve()),
        edge_blur_px=round(float(np.median(found)), 3) if (found := [b for b in seg.blurs if b is not None]) else None,
    )
    return result, fits, chosen, {"inner": inner, "counts": counts, "noise": noise, "edge": edge}


def _segmentation_found(s: ProfileSettings, params, scale, seg: Segmented, sized: int) -> SegmentationFound:
    grown = seg.grown
    return SegmentationFound(
        scale_px=params.scale,
        scale_estimate=scale.as_dict() if scale else None,
        setting={k: v for k, v in s.segment.as_dict().items() if v != SegmentParams().as_dict()[k]},
        separability_median=round(float(np.median(seg.separabilities)), 4),
        # images whose outlines grew out to the particles' edges, and the foreground added (median over those)
        outlines_grown={
            "images": sum(g > 0 for g in grown),
            "foreground_added_median": round(float(np.median([g for g in grown if g > 0] or [0.0])), 4),
        },
        params=params.as_dict(),
        particles=int(sum(len(t["diameter_px"]) for t in seg.tables)),
        particles_not_touching_border=int(sized),
    )


def _patch_counts(window: int, patch: int, counts: np.ndarray, whole: np.ndarray) -> PatchCounts:
    return PatchCounts(
        definition=f"segments (any, border-touching included) whose centroid lies inside a "
        f"{window} px window; windows on a grid of stride {window // 2} px",
        patch_size=window,
        windows=int(counts.size),
        mean=round(float(counts.mean()), 3),
        median=float(np.median(counts)),
        p10=float(np.quantile(counts, 0.1)),
        p90=float(np.quantile(counts, 0.9)),
        # The windows training keeps (data.min_particles: 3 by default): the scene's range.
        with_3_or_more=_quantiles(counts[counts >= 3]),
        kept_counts={str(k): _quantiles(counts[counts >= k]) for k in (1, 2, 3)},
        render_px=patch if window != patch else None,
        whole={
            "stride": STRIDE,
            "windows": int(whole.size),
            **{f"at_least_{k}": int((whole >= k).sum()) for k in (1, 2, 3)},
        },
    )


def write_profile(s: ProfileSettings, result, images, seg: Segmented, sizes, fits, chosen, polarity, scale):
    """The figures, the material (its parent chosen from the result), profile.json and report.md; the result with
    the material it proposed."""
    out = s.out
    figures.write_figures(
        out, images, seg.labels_kept, sizes["inner"], fits, chosen, sizes["noise"], seg.foregrounds, sizes["counts"],
        polarity,
    )  # fmt: skip
    if scale is not None:
        figures.scale_figure(out, scale.as_dict())
    figures.edge_figure(out, sizes["edge"])
    parent, yaml_text = material_yaml(result, fits, chosen)
    fringe = fringe_settings(result.edge)[0] if parent_renders_fringe(parent) else None
    result = replace(
        result,
        material=MaterialProposed(
            parent=parent,
            config=str(s.conf_path.resolve()),
            data=data_settings(result)[0],
            fringe=fringe,  # material.imaging.fringe as written (None: the material renders no fringe)
        ),
    )
    write_json(out / "profile.json", result.as_dict())
    write_bytes(out / "report.md", report_markdown(result).encode())
    write_bytes(s.conf_path, yaml_text.encode())
    log.info("wrote %s and %s (parent material %s)", out / "profile.json", s.conf_path, parent)
    return result


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
    shown = [lab if lab is not None else np.zeros(im.shape, np.int32) for im, lab in zip(images, labels)][:4]
    figures.outline_figure(out, images, shown, polarity)


def _quantiles(counts: np.ndarray) -> dict:
    if counts.size == 0:
        return {"windows": 0, "p10": None, "p90": None}
    return {"windows": int(counts.size), "p10": float(np.quantile(counts, 0.1)), "p90": float(np.quantile(counts, 0.9))}


# --- the report -------------------------------------------------------------------------------------------


def report_markdown(result: ProfileResult) -> str:
    """report.md: what the profile measured and what the material config it wrote says."""
    sizes = result.sizes
    fits = "\n".join(
        f"| {f['kind']}{' (chosen)' if f['kind'] == sizes.chosen else ''} | "
        + ", ".join(f"{k} {v:g}" for k, v in f["params"].items())
        + f" | {f['log_likelihood']:.1f} | {f['bic']:.1f} |"
        for f in sizes.fits
    )
    return (
        _report_head(result)
        + _segmentation_markdown(result)
        + f"""
## Diameter fits ({sizes.criterion})

| fit | parameters (px; sigma of log d) | log L | BIC |
|---|---|---|---|
{fits}
"""
        + edge_markdown(result.edge, result.material)
        + "\nFigures: `sizes.png`, `scale_search.png`, `particles.png` (real images: keep them out of repositories), "
        "`background_noise.png`, `edge_profile.png`.\n"
    )


def edge_markdown(edge: dict | None, material: MaterialProposed) -> str:
    """The report's section on the mean particle edge: the ring the rule found, the fit, what the material got."""
    written = material.fringe
    parent_takes = parent_renders_fringe(material.parent)
    if written is not None:
        verdict = f"written: `material.imaging.fringe: {written}`"
    elif parent_takes:
        verdict = "none written: the material renders no fringe"
    else:
        verdict = f"not written: the parent material `{material.parent}` renders no fringe (transmission only)"
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
({EDGE_OUTSIDE_PX}-{EDGE_BACKGROUND_PX} px outside), 1 = its interior ({EDGE_INTERIOR_PX}-{EDGE_INSIDE_PX} px \
inside). Rule: {edge["rule"]}. Fringe: {verdict}.

{table}

{bins}
"""


def _report_head(r: ProfileResult) -> str:
    b, c, a, px = r.background, r.particles_per_patch, r.agglomeration, r.pixel_size
    from drgan.segmenters.contacts import resolve_contact_weight

    contact = resolve_contact_weight("auto", r.polarity.value, a.clark_evans_median)[1].removeprefix("auto: ")
    return f"""# Profile: {r.name}

{r.data.images} image(s) of `{r.data.dir}` (crop_rows {r.data.crop_rows}, split {r.data.split}).
Material config: `{r.material.config}` (parent `{r.material.parent}`).

| quantity | value |
|---|---|
| polarity | {r.polarity.value} ({r.polarity.setting}; confidence {r.polarity.confidence}) |
| background grey (median of background pixels) | {b.background_grey:.4f} |
| noise sigma (MAD of the high-pass residual, corrected) | {b.noise_sigma:.4f} |
| lag-1 autocorrelation of the residual | {b.lag1_autocorrelation:.3f} |
| grain (Gaussian stddev, px) | {b.grain_px:.2f} |
| outline blur (Gaussian stddev of the steepest edge slope, px) | \
{"not measured" if r.edge_blur_px is None else f"{r.edge_blur_px:.2f}"} |
| particles segmented / not touching the border | {r.segmentation.particles} / \
{r.segmentation.particles_not_touching_border} |
| median / mean equivalent diameter (px), at half contrast | {r.sizes.median_diameter_px:.2f} / \
{r.sizes.mean_diameter_px:.2f} |
| half contrast from the segmented outlines (px, > 0 outwards) | {_shift_text(r.sizes)} |
| particles per {c.patch_size} px patch: mean / median (p10-p90) | {c.mean:.2f} / {c.median:g} ({c.p10:g}-{c.p90:g}) |
| touching fraction / Clark-Evans ratio | {a.touching_fraction:.3f} / {a.clark_evans_median} \
-> placement {a.placement} |
| median axis ratio | {r.shape.axis_ratio_median:.3f} -> meshes {r.shape.mesh_kind} |
| pixel size | {px.nm_per_px} nm ({px.source}) |

Particles per patch: {c.definition}.
A segmenter trained on this material's pairs (`drgan.segment model.contact_weight=auto`) takes contact weight {contact}.
"""


def _warn_mixed_polarity(estimate, paths: list[Path]) -> None:
    """One material is proposed for the whole folder: images that look like the other polarity are named (a folder
    mixing SEM and TEM images, or two materials, wants a profile per kind; or one image misread: set the polarity)."""
    other = [p.name for p, vote in zip(paths, estimate.votes) if vote.polarity not in (None, estimate.polarity)]
    if other:
        log.warning(
            "polarity: %d of %d image(s) look like %s particles, not %s: %s. One material is proposed for the whole "
            "folder: if it mixes imaging modes (SEM and TEM) or materials, profile each kind in its own folder; if "
            "they are misread, set data.polarity=%s",
            len(other), len(paths), "dark" if estimate.polarity == "bright" else "bright", estimate.polarity,
            ", ".join(other[:5]) + (" ..." if len(other) > 5 else ""), estimate.polarity,
        )  # fmt: skip


def _shift_text(sizes) -> str:
    if sizes.segmented_median_diameter_px is None:
        return "not measured (sizes at the segmented outlines)"
    if sizes.outline_shift_px == 0:
        return "0: no mean edge to place it (sizes at the segmented outlines)"
    return (
        f"{sizes.outline_shift_px:+.2f}: every diameter {2 * sizes.outline_shift_px:+.2f} px (median at the segmented "
        f"outlines {sizes.segmented_median_diameter_px:.2f}); drgan's masks end at half contrast (ISO 13322-1)"
    )


def _segmentation_markdown(r: ProfileResult) -> str:
    """The segmentation table: each data.segment key the material carries, and why it has its value."""
    data, data_notes = data_settings(r)
    given = r.segmentation.setting
    table = "| key | value | why |\n|---|---|---|\n" + "\n".join(
        f"| data.segment.{k} | {v} | {'set by hand' if k in given else WHY_SEGMENT.get(k, 'from the scale')} |"
        for k, v in data["segment"].items()
    )
    notes = "\n".join(f"- `{k}`: {v}" for k, v in data_notes.items())
    return f"""## Segmentation (drgan.data.classical; written to the material's `data` keys, so training mines alike)

{table}

{notes}
"""


@stage_main("conf/gan", "profile")
def main(cfg: DictConfig):
    OmegaConf.resolve(cfg)
    profile(ProfileSettings.from_config(cfg))


if __name__ == "__main__":
    start(main)
