"""`python -m drgan.generate ckpt=RUN_OR_CKPT n=1000 out=DIR`: a synthetic segmentation training set.

For each index i = 0, 1, 2, ... a new constellation phi_i is drawn from the material's size and placement
distributions, rendered by the trained generator (no gradients) and annotated exactly: instance labels from
the renderer, and the 3-class mask (0 background, 1 particle, 2 contour of ``contour_px``). Images whose
particles are not clearly distinguishable are dropped (``contrast_check``); indices go on until n are kept.
Then ``n_background`` real background patches are added with all-zero masks. When the PatchSet holds fewer
windows free of particles (dense images), ``partial_background`` (default true) fills up with real windows that
hold particles: their masks are 0 on the background and IGNORE (255) on the particles found by the classical
segmentation, grown by a margin, which a segmenter's loss leaves out (drgan.synthetic.backgrounds: the margin, and
the windows skipped because they ignore more than ``partial_max_ignored`` of their pixels).

The folder DIR, its items and manifest.json are drgan.synthetic's (folder, manifest, shards); this module is the
render loop and its command line. IDs: ``syn_000123`` (123 = the index; dropped indices leave gaps), ``bg_0000``,
``pbg_0000`` (partial backgrounds).

Reproducible and resumable: index i uses seeds from ``SeedSequence([seed, i])`` only, so its image does not
depend on which process renders it or when. ``meta/ID.json`` (kept) or ``dropped/ID.json`` is written last
and marks an index done; a re-run with the same settings skips done indices and completes a partial
dataset; it first removes what a killed run left of its own indices (temporary files, PNGs of an index
without its record), so no image is ever left without its mask. A re-run with different settings
(checkpoint, seed, filter, renderer, partial-background settings, ...) into the same folder is refused; n and
n_background may grow.

Sharding: ``shard=i/k`` renders only indices with index % k == i; all shards write into one DIR (a shared
file system). The dataset is the first n kept indices (as in a single process), so a shard stops at index j
once the indices below j known to be kept, its own and those the other shards have finished, number n.
Shards run at the same time share the work evenly; run one after the other, the first does most of it.
Each shard writes ``manifest_shard_i.json``; whichever finds the dataset complete (all indices up to the
n-th kept and all backgrounds done; shard 0 adds the backgrounds and partial backgrounds) writes ``manifest.json``. If none could
(e.g. a shard failed), run the same command with ``merge=true``: it renders nothing and writes the
manifest, or says which indices are missing. Kept indices beyond the n-th (rendered by a shard that could
not yet know) stay on disk but are not in the manifest.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drgan.core.errors import DataError
from drgan.core.progress import Task
from drgan.data.polarity import check_polarity
from drgan.launch.runtime import stage_main, start
from drgan.scene.labels import class_mask
from drgan.synthetic.backgrounds import write_backgrounds
from drgan.synthetic.folder import DatasetFolder, syn_id
from drgan.synthetic.generation_settings import GenerateSettings
from drgan.synthetic.grey_spread import GreySpread
from drgan.synthetic.manifest import material_facts, write_manifest, write_shard_manifest
from drgan.synthetic.shards import Shard, kept_below, owned_by
from drgan.synthetic.source import load_module, use_parameters

log = logging.getLogger(__name__)

EARLY_ATTEMPTS = 50  # renders after which a run that kept none stops (the filter and the generator disagree)


def index_seeds(seed: int, index: int) -> dict[str, int]:
    """Independent 31-bit seeds for the layout and the render of index i (the render seed fixes both the
    sample pattern and the additive noise, drgan.models.generator.add_noise)."""
    phi, render = (int(s) & 0x7FFFFFFF for s in np.random.SeedSequence([int(seed), int(index)]).generate_state(2))
    return {"phi": phi, "render": render}


# --- the filter ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    kept: bool
    reason: str | None  # why dropped: "no_particle", "background_fraction", "contrast"
    contrast: float  # how far particles stand out: particle / background mean (bright), background / particle (dark)
    background_fraction: float
    particles_visible: int


def contrast_check(
    image: np.ndarray, labels: np.ndarray, min_contrast: float, min_background: float, polarity: str = "bright"
) -> Check:
    """Are the particles of ``image`` (H, W, [0, 1]) clearly distinguishable, given its instance ``labels``?

    Dropped when no particle is visible, when less than ``min_background`` of the pixels are background
    (the contrast would be measured on a few stray pixels), or when the particles do not stand out from the
    background by the factor ``min_contrast`` in the data's direction (the paper's filter, 1.15): for bright
    particles the mean particle intensity must reach min_contrast x the mean background intensity, for dark
    particles (``polarity="dark"``) the mean background intensity must reach min_contrast x the particles'.
    """
    check_polarity(polarity, "polarity")
    image, labels = np.asarray(image, dtype=np.float64), np.asarray(labels)
    if image.shape != labels.shape:
        raise DataError(f"contrast_check: image {image.shape} and labels {labels.shape} differ in shape")
    particle = labels > 0
    visible = int(len(np.unique(labels[particle])))
    background_fraction = float(1.0 - particle.mean())
    if not visible:
        return Check(False, "no_particle", math.nan, background_fraction, 0)
    if background_fraction == 0.0:
        return Check(False, "background_fraction", math.nan, background_fraction, visible)
    fg, bg = float(image[particle].mean()), float(image[~particle].mean())
    if polarity == "dark":
        fg, bg = bg, fg
    contrast = fg / bg if bg > 0 else (math.inf if fg > 0 else math.nan)
    if background_fraction < min_background:
        return Check(False, "background_fraction", contrast, background_fraction, visible)
    if not contrast >= min_contrast:  # NaN (all black) fails too
        return Check(False, "contrast", contrast, background_fraction, visible)
    return Check(True, None, contrast, background_fraction, visible)


# --- the render loop ------------------------------------------------------------------------------------


class Stats:
    def __init__(self):
        self.rendered = self.kept = self.dropped = self.skipped = 0
        self.render_s = self.label_s = 0.0
        self.start = time.perf_counter()
        self.reasons: Counter = Counter()
        self.contrasts: list[float] = []  # of the images rendered in this run

    def as_dict(self) -> dict:
        wall = time.perf_counter() - self.start
        return {
            "rendered": self.rendered,
            "kept": self.kept,
            "dropped": self.dropped,
            "skipped_done": self.skipped,
            "drop_reasons": dict(self.reasons),
            "wall_s": round(wall, 3),
            "render_s": round(self.render_s, 3),
            "label_s": round(self.label_s, 3),
            "kept_per_minute": round(60.0 * self.kept / wall, 3) if self.rendered and wall > 0 else None,
            "rendered_per_minute": round(60.0 * self.rendered / wall, 3) if self.rendered and wall > 0 else None,
        }


class Rendered(NamedTuple):
    """One synthetic index, rendered, annotated and judged (`render_index`)."""

    image: np.ndarray  # (H, W) in [0, 1], after grey_spread
    labels: np.ndarray  # instance ids, 0 background
    mask: np.ndarray  # 0 background, 1 particle, 2 contour
    check: Check  # the filter's verdict
    meta: dict  # meta/ID.json (or dropped/ID.json with the reason) without its id and files
    render_s: float  # seconds in the renderer
    label_s: float  # seconds making the mask


def render_index(
    module, sample_phi, settings: GenerateSettings, index: int, spread: GreySpread | None = None
) -> Rendered:
    """Index ``index`` rendered, annotated and judged, reproducible from (seed, index); with ``spread``
    (grey_spread) the image takes one real patch's grey levels."""
    seeds = index_seeds(settings.seed, index)
    phi = sample_phi(seeds["phi"])
    start = time.perf_counter()
    sample = module.generator.sample(phi, seed=seeds["render"])
    render_s = time.perf_counter() - start
    start = time.perf_counter()
    labels = np.asarray(sample.labels)
    mask = class_mask(labels, settings.contour_px)
    label_s = time.perf_counter() - start
    image, grey = sample.image, None
    if spread is not None:  # grey_spread: this image's grey levels from a real patch
        image, grey = spread.apply(image, labels, seeds["render"])
    check = contrast_check(image, labels, settings.min_contrast, settings.min_background, settings.polarity)
    sigma_key = module.generator.material.noise_sigma.key
    meta = {
        "kind": "synthetic",
        "index": index,
        "seed": seeds,
        "phi": np.asarray(sample.phi).tolist(),
        "phi_columns": ["x_px", "y_px", "z_px", "scale_px"],
        "parameters": sample.parameters,
        "sigma": sample.parameters.get(sigma_key),
        "contrast": check.contrast,
        "background_fraction": check.background_fraction,
        "particles_visible": check.particles_visible,
    }
    if grey is not None:
        meta["grey_spread"] = grey
    return Rendered(image, labels, mask, check, meta, render_s, label_s)


def generate(cfg: DictConfig) -> dict:
    """Render this shard's part of the dataset in ``cfg.out``; return the manifest written (merged or shard)."""
    return generate_dataset(GenerateSettings.from_config(cfg))


def pairs_pixel_scale(resolution: int, backgrounds, view_width: float) -> float:
    """Image px of the pairs per px of the real images the GAN learned from: the render resolution over the real
    window its training patches covered (the run's PatchSet; below 1 when large particles were learned from windows
    wider than the render), else over the material's view (a generator without patches, e.g. imported)."""
    from drgan.data.patches import PatchSet

    window = PatchSet.saved_window(backgrounds) if backgrounds else None
    return round(resolution / float(window or view_width), 6)


def generate_dataset(given: GenerateSettings) -> dict:
    """Render this shard's part of the dataset in ``given.out`` (settings as given: resolved against the checkpoint
    here); return the manifest written (merged or shard)."""
    settings, saved_cfg, material = given.resolve()
    out = Path(str(settings.out)).expanduser().resolve()
    folder = DatasetFolder(out)
    shard = Shard.parse(settings.shard)
    folder.check_settings(settings.fixed())
    facts = material_facts(material)
    if settings.merge:
        return write_manifest(folder, settings, stats=None, required=True, material=facts)
    folder.remove_partial(lambda item: owned_by(item, shard))
    module, spread, patches = _generator(settings, saved_cfg, material)
    resolution = int(module.generator.scene.spec.render.resolution)
    pixel_scale = pairs_pixel_scale(resolution, settings.backgrounds, module.generator.scene.spec.view_width)
    log.info(
        "generating %d images of %s into %s (shard %s, %d x %d px, spp %s, contour %d px)",
        settings.n, settings.material, out, shard, resolution, resolution,
        module.generator.scene.spec.render.spp, settings.contour_px,
    )  # fmt: skip
    if shard.index == 0:
        write_backgrounds(
            folder, settings.backgrounds, settings.n_background, resolution, settings.partial, settings.polarity
        )
    stats = render_shard(folder, module, OmegaConf.create(saved_cfg), settings, shard, spread)
    summary = stats.as_dict()
    rate = summary["kept_per_minute"]
    print(f"{stats.kept} kept, {stats.dropped} dropped, {stats.skipped} already done; "
          + (f"{rate:.2f} images/minute ({summary['rendered_per_minute']:.2f} rendered/minute)" if rate is not None else "nothing rendered"))  # fmt: skip
    if shard.count > 1:
        write_shard_manifest(folder, settings, shard, summary, pixel_scale)
    manifest = write_manifest(
        folder,
        settings,
        stats=summary,
        required=shard.count == 1,
        pixel_scale=pixel_scale,
        material=facts,
    )
    if manifest is not None:
        counts = manifest["counts"]
        print(f"dataset {out}: {counts['synthetic']} synthetic, {counts['background']} background and "
              f"{counts['partial_background']} partial background items (n_background={settings.n_background})")  # fmt: skip
        write_checks(out, manifest, settings, resolution, patches)
    return manifest


def _generator(settings, saved_cfg: dict, material):
    """(the checkpoint's GAN module with the settings' parameters, the grey spread or None, the real patches or
    None): the patches are loaded once where something needs them (texture, grey spread, the checks)."""
    module = load_module(Path(settings.ckpt), saved_cfg, material)
    use_parameters(module, settings.parameters, saved_cfg)
    resolution = int(module.generator.scene.spec.render.resolution)
    spread = None  # with grey_spread, the real patches' grey levels each image takes one of
    patches = None
    if module.textured or settings.grey_spread:
        from drgan.data.patches import PatchSet

        patches = PatchSet.load(settings.backgrounds)
        if module.textured:
            module.use_background_texture(patches.background)
        if settings.grey_spread:
            spread = GreySpread.from_patches(
                patches.train, patches.params.get("segment") or {}, settings.polarity, resolution
            )
            levels = spread.levels
            log.info(
                "grey_spread: grey levels of %d real train patches: background %.3f-%.3f, particles %.3f-%.3f "
                "(5th-95th percentile); each image's own measured by the same segmentation",
                len(levels), *np.quantile(levels[:, 0], [0.05, 0.95]), *np.quantile(levels[:, 1], [0.05, 0.95]),
            )  # fmt: skip
    return module, spread, patches


def render_shard(folder: DatasetFolder, module, model_cfg, settings, shard: Shard, spread) -> Stats:
    """The shard's indices rendered in order until n pairs are kept below the next index (the other shards' too),
    each written (or its drop recorded) as it is done; indices finished before are skipped, so a rerun resumes."""
    import torch

    from drgan.models import build

    layouts = build.layout_sampler(model_cfg)  # built once: typing the material per image costs ~25 ms

    def sample_phi(seed: int) -> np.ndarray:
        return layouts(1, seed=seed)[0]

    n, stats = settings.n, Stats()
    outcomes = folder.outcomes()
    bar = _progress(settings.progress, total=math.ceil(n / shard.count))
    already = sum(1 for i, kept in outcomes.items() if kept and i % shard.count == shard.index)
    task = Task("rendering pairs", math.ceil(n / shard.count), "pairs", start=min(already, math.ceil(n / shard.count)))
    index = shard.index
    try:
        with torch.no_grad():
            while True:
                if kept_below(outcomes, index) < n and shard.count > 1:
                    outcomes = folder.outcomes()  # what the other shards finished meanwhile
                if kept_below(outcomes, index) >= n:
                    break
                _check_progress(stats, settings, outcomes, index)
                item = syn_id(index)
                if index in outcomes and (not outcomes[index] or folder.done(item)):
                    stats.skipped += 1
                    index += shard.count
                    continue
                rendered = render_index(module, sample_phi, settings, index, spread)
                check = rendered.check
                stats.rendered += 1
                stats.contrasts.append(check.contrast)
                stats.render_s += rendered.render_s
                stats.label_s += rendered.label_s
                if check.kept:
                    folder.write(item, rendered.image, rendered.mask, rendered.labels, rendered.meta)
                    stats.kept += 1
                    bar.update(1)
                    task.advance()
                else:
                    folder.write_dropped(item, {"reason": check.reason, **rendered.meta})
                    stats.dropped += 1
                    stats.reasons[check.reason] += 1
                outcomes[index] = check.kept
                bar.set_postfix(kept=stats.kept, dropped=stats.dropped, skipped=stats.skipped, refresh=False)
                index += shard.count
    finally:
        bar.close()
    task.close()
    return stats


def _check_progress(stats: Stats, settings, outcomes: dict, index: int) -> None:
    """A RuntimeError where generation is stuck: none of the first images passed the filter, or max_attempts
    indices gave fewer than n pairs (what dropped them, and what to change)."""
    if stats.rendered >= EARLY_ATTEMPTS and stats.kept == 0 and kept_below(outcomes, index) == 0:
        contrasts = np.asarray(stats.contrasts, dtype=np.float64)
        median = float(np.nanmedian(contrasts)) if np.isfinite(contrasts).any() else math.nan
        raise RuntimeError(
            f"none of the first {stats.rendered} images passed the filter (drop reasons: {dict(stats.reasons)}; "
            f"median contrast {median:.3f} against min_contrast={settings.min_contrast} for "
            f"{settings.polarity} particles, min_background={settings.min_background}). A contrast "
            "below 1 means the particles are on the wrong side of the background: check polarity (here "
            "from the checkpoint's material) and the epoch (best_epoch.json); or lower min_contrast"
        )
    if index >= settings.max_attempts:
        have = kept_below(outcomes, index)
        raise RuntimeError(
            f"only {have} of n={settings.n} images passed the filter in max_attempts={settings.max_attempts} "
            f"indices (drop reasons this run: {dict(stats.reasons) or 'none'}; min_contrast="
            f"{settings.min_contrast}, min_background={settings.min_background}): lower min_contrast "
            "or min_background, raise max_attempts, or pick a better checkpoint"
        )


def write_checks(out: Path, manifest: dict, settings, resolution: int, patches=None) -> dict[str, dict]:
    """The generated set against the real train patches (``patches``: the PatchSet already loaded, else
    settings.backgrounds'), each check a module of drgan.synthetic with check_dataset and log_result: noise_check.json
    (fine-scale noise), edge_check.json with edge_check.png (the mean particle edge), contact_check.json (contacts
    whose neck the image hides); each logged, with a warning where the set is far from the images. Nothing without
    real patches (an imported generator). Seconds: 64 images on each side per check."""
    from drgan.core.io import write_bytes, write_json
    from drgan.synthetic import contact_check, edge_check, noise_check

    written = {}
    for name, check in (("noise_check", noise_check), ("edge_check", edge_check), ("contact_check", contact_check)):
        result = check.check_dataset(
            out, manifest, settings.backgrounds if patches is None else patches, settings.polarity, resolution
        )
        if result is None:
            continue
        write_json(out / f"{name}.json", result)
        if hasattr(check, "figure"):
            write_bytes(out / f"{name}.png", check.figure(result))
        check.log_result(result)
        written[name] = result
    return written


def _progress(shown: bool, total: int):
    """The tqdm bar on a terminal; off one (a log file, the pipeline's child, a SLURM job) drgan.core.progress's lines say
    the same, once a minute, and a bar would only repeat itself into the log."""
    import sys

    from tqdm import tqdm

    return tqdm(total=total, desc="kept", unit="img", disable=not shown or not sys.stderr.isatty(), dynamic_ncols=True)


@stage_main("conf/gan", "generate")
def main(cfg: DictConfig) -> None:
    generate(cfg)


if __name__ == "__main__":
    start(main)
