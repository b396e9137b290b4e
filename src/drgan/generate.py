"""`python -m drgan.generate ckpt=RUN_OR_CKPT n=1000 out=DIR`: a synthetic segmentation training set.

For each index i = 0, 1, 2, ... a new constellation phi_i is drawn from the material's size and placement
distributions, rendered by the trained generator (no gradients) and annotated exactly: instance labels from
the renderer, and the 3-class mask (0 background, 1 particle, 2 contour of ``contour_px``). Images whose
particles are not clearly distinguishable are dropped (``contrast_check``); indices go on until n are kept.
Then ``n_background`` real background patches are added with all-zero masks.

Layout of DIR (every file written atomically through drgan.io):
    images/ID.png   8-bit grey           masks/ID.png   uint8 {0, 1, 2}
    labels/ID.png   instance ids (16-bit when > 255)    meta/ID.json   phi, parameters, sigma, seeds, contrast
    dropped/ID.json why an index was dropped            config.json    the settings that fix every index
    manifest.json   the dataset: entries (id, kind, index, files), config, counts, throughput
IDs: ``syn_000123`` (123 = the index; dropped indices leave gaps), ``bg_0000``.

Reproducible and resumable: index i uses seeds from ``SeedSequence([seed, i])`` only, so its image does not
depend on which process renders it or when. ``meta/ID.json`` (kept) or ``dropped/ID.json`` is written last
and marks an index done; a re-run with the same settings skips done indices and completes a partial
dataset; it first removes what a killed run left of its own indices (temporary files, PNGs of an index
without its record), so no image is ever left without its mask. A re-run with different settings
(checkpoint, seed, filter, renderer, ...) into the same folder is refused; n and n_background may grow.

Sharding: ``shard=i/k`` renders only indices with index % k == i; all shards write into one DIR (a shared
file system). The dataset is the first n kept indices (as in a single process), so a shard stops at index j
once the indices below j known to be kept, its own and those the other shards have finished, number n.
Shards run at the same time share the work evenly; run one after the other, the first does most of it.
Each shard writes ``manifest_shard_i.json``; whichever finds the dataset complete (all indices up to the
n-th kept and all backgrounds done; shard 0 adds the backgrounds) writes ``manifest.json``. If none could
(e.g. a shard failed), run the same command with ``merge=true``: it renders nothing and writes the
manifest, or says which indices are missing. Kept indices beyond the n-th (rendered by a shard that could
not yet know) stay on disk but are not in the manifest.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from drgan import io
from drgan.data.polarity import check_polarity
from drgan.errors import ConfigError, DataError
from drgan.scene.labels import class_mask

log = logging.getLogger(__name__)

SYN, BG = "syn", "bg"
FILE_KINDS = ("images", "masks", "labels")  # PNGs; meta/ID.json comes last
# drgan.io.atomic_path's temporary name for a file NAME: ".NAME.<random>.tmp<suffix of NAME>".
_TEMP_NAME = re.compile(r"^\.(?P<target>.+)\.[A-Za-z0-9_]+\.tmp(\.[A-Za-z0-9]+)?$")
# Settings that decide what each index holds: a dataset folder is only ever completed with the same ones.
FIXED_SETTINGS = ("ckpt", "material", "seed", "contour_px", "min_contrast", "min_background", "polarity", "renderer",
                  "backgrounds")
EARLY_ATTEMPTS = 50  # renders after which a run that kept none stops (the filter and the generator disagree)


def syn_id(index: int) -> str:
    return f"{SYN}_{index:06d}"


def bg_id(index: int) -> str:
    return f"{BG}_{index:04d}"


def index_seeds(seed: int, index: int) -> dict[str, int]:
    """Independent 31-bit seeds for the layout and the render of index i (the render seed fixes both the
    sample pattern and the additive noise, drgan.models.generator.add_noise)."""
    phi, render = (int(s) & 0x7FFFFFFF for s in np.random.SeedSequence([int(seed), int(index)]).generate_state(2))
    return {"phi": phi, "render": render}


@dataclass(frozen=True)
class Shard:
    index: int
    count: int

    @classmethod
    def parse(cls, text) -> Shard:
        """"i/k" with 0 <= i < k; None or "" is the whole range (0/1)."""
        if text in (None, "", "null"):
            return cls(0, 1)
        parts = str(text).split("/")
        try:
            i, k = (int(p) for p in parts)
        except ValueError:
            i, k = -1, 0
        if len(parts) != 2 or k < 1 or not 0 <= i < k:
            raise ConfigError(f"shard={text!r}: expected 'i/k' with integers 0 <= i < k, e.g. shard=0/4")
        return cls(i, k)

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


# --- the filter ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    kept: bool
    reason: str | None  # why dropped: "no_particle", "background_fraction", "contrast"
    contrast: float  # how far particles stand out: particle / background mean (bright), background / particle (dark)
    background_fraction: float
    particles_visible: int


def contrast_check(image: np.ndarray, labels: np.ndarray, min_contrast: float, min_background: float,
                   polarity: str = "bright") -> Check:
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


# --- inputs -------------------------------------------------------------------------------------------------


def resolve_checkpoint(ckpt) -> tuple[Path, Path | None]:
    """A checkpoint file or a run folder -> (checkpoint file, run folder or None)."""
    if ckpt in (None, "", "???"):
        raise ConfigError("ckpt: expected a checkpoint file or a training run folder (with checkpoints/best.ckpt)")
    path = Path(str(ckpt)).expanduser().resolve()
    if path.is_dir():
        best = path / "checkpoints" / "best.ckpt"
        if not best.is_file():
            raise ConfigError(f"ckpt={ckpt}: a folder without checkpoints/best.ckpt (expected a training run folder or a .ckpt file)")
        return best, path
    if not path.is_file():
        raise ConfigError(f"ckpt={ckpt}: no such checkpoint file or run folder")
    run = path.parent.parent if path.parent.name == "checkpoints" else None
    return path, run


def checkpoint_config(ckpt_file: Path) -> dict:
    """The model config (material, size, placement, renderer, model, seed) saved with a GANModule checkpoint."""
    from drgan.checkpoint_io import load_checkpoint

    checkpoint = load_checkpoint(ckpt_file, "ckpt", expected="a .ckpt written by drgan.train")
    cfg = (checkpoint.get("hyper_parameters") or {}).get("cfg")
    if not isinstance(cfg, dict) or "material" not in cfg:
        raise ConfigError(f"ckpt={ckpt_file}: no drgan model config in its hyperparameters (not a GANModule checkpoint?)")
    return cfg


def effective_renderer(saved: dict, overrides) -> dict:
    renderer = dict(saved or {})
    renderer.update({k: v for k, v in (OmegaConf.to_container(overrides) if isinstance(overrides, DictConfig) else dict(overrides or {})).items() if v is not None})
    return renderer


def load_module(ckpt_file: Path, model_cfg: dict):
    """GANModule in eval mode, rebuilt with ``model_cfg`` (the saved one, renderer possibly overridden)."""
    from drgan.checkpoint_io import refusing_unsafe
    from drgan.models.gan_module import GANModule

    with refusing_unsafe("ckpt", ckpt_file):
        module = GANModule.load_from_checkpoint(ckpt_file, map_location="cpu", cfg=model_cfg, weights_only=True)
    module.eval()
    return module


def load_backgrounds(path: Path | None, n: int, resolution: int) -> tuple[list[np.ndarray], list[dict]]:
    """Up to n background patches of a PatchSet, resized (bicubic, on floats) when their size is not the render's."""
    if n == 0:
        return [], []
    from drgan.data.patches import PatchSet

    if path is None:
        raise ConfigError(f"n_background={n}: no background patches found; give backgrounds=PATCHSET_FOLDER (a run's patches/) or n_background=0")
    patches = PatchSet.load(path)
    if len(patches.background) < n:
        log.warning("backgrounds=%s holds %d background patches, fewer than n_background=%d: using all", path, len(patches.background), n)
    images, sources = [], []
    for k in range(min(n, len(patches.background))):
        patch = np.asarray(patches.background[k], dtype=np.float32)
        if patch.shape != (resolution, resolution):
            from PIL import Image

            patch = np.asarray(Image.fromarray(patch, mode="F").resize((resolution, resolution), Image.BICUBIC), dtype=np.float32)
        images.append(np.clip(patch, 0.0, 1.0))
        sources.append({
            "patchset": str(path),
            "image_id": patches.background_ids[k],
            "position": [int(v) for v in patches.background_positions[k]],
            "foreground_fraction": float(patches.background_fractions[k]),
            "patch_size": int(patches.background[k].shape[-1]),
        })  # fmt: skip
    return images, sources


# --- the dataset folder -------------------------------------------------------------------------------------


class DatasetFolder:
    """Files of one generated dataset; an index is done when its meta (kept) or dropped record exists."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def files(self, item: str) -> dict[str, str]:
        names = {kind.rstrip("s"): f"{kind}/{item}.png" for kind in FILE_KINDS}
        names["meta"] = f"meta/{item}.json"
        return names

    def done(self, item: str) -> bool:
        return all((self.root / f).is_file() for f in self.files(item).values())

    def outcomes(self) -> dict[int, bool]:
        """index -> kept (True) / dropped (False), for every finished synthetic index (file names only)."""
        found: dict[int, bool] = {}
        for folder, kept in (("dropped", False), ("meta", True)):
            directory = self.root / folder
            if not directory.is_dir():
                continue
            for entry in os.scandir(directory):
                name = entry.name
                if name.startswith(SYN + "_") and name.endswith(".json") and name[4:-5].isdigit():
                    found[int(name[4:-5])] = kept or found.get(int(name[4:-5]), False)
        return found

    def write(self, item: str, image: np.ndarray, mask: np.ndarray, labels: np.ndarray, meta: dict) -> None:
        for kind, array in (("images", image), ("masks", mask), ("labels", labels)):
            io.write_png(self.root / kind / f"{item}.png", array)
        io.write_json(self.root / "meta" / f"{item}.json", {"id": item, **meta, "files": self.files(item)})

    def write_dropped(self, item: str, record: dict) -> None:
        io.write_json(self.root / "dropped" / f"{item}.json", {"id": item, **record})

    def remove_partial(self, owns) -> dict[str, int]:
        """Remove what a killed run left of the items this process owns (``owns(item) -> bool``): temporary files
        of drgan.io's atomic writes (a SIGKILL skips their clean-up), and the PNGs of items without their
        meta/ID.json or dropped/ID.json record (killed between an item's files: meta comes last). Such an item
        is not done, so this run renders it again; removing its files first means that no image is ever left
        without its mask, whatever n the next run asks for. Returns the counts removed, by kind."""
        removed = {"temporary": 0, "unpaired": 0}
        for folder in (*FILE_KINDS, "meta", "dropped"):
            directory = self.root / folder
            if not directory.is_dir():
                continue
            for entry in os.scandir(directory):
                temp = _TEMP_NAME.match(entry.name)
                if temp:
                    if owns(Path(temp["target"]).stem):
                        os.unlink(entry.path)
                        removed["temporary"] += 1
                elif folder in FILE_KINDS and entry.name.endswith(".png"):
                    item = entry.name[: -len(".png")]
                    recorded = any((self.root / kind / f"{item}.json").is_file() for kind in ("meta", "dropped"))
                    if owns(item) and not recorded:
                        os.unlink(entry.path)
                        removed["unpaired"] += 1
        for entry in os.scandir(self.root) if self.root.is_dir() else ():
            temp = _TEMP_NAME.match(entry.name)
            if temp and owns(Path(temp["target"]).stem):  # config.json, manifest*.json
                os.unlink(entry.path)
                removed["temporary"] += 1
        if any(removed.values()):
            log.warning("%s: removed %d temporary file(s) and %d file(s) of unfinished items left by an interrupted run",
                        self.root, removed["temporary"], removed["unpaired"])
        return removed

    def check_settings(self, settings: dict) -> None:
        """Record the settings at first use; refuse to complete a folder made with other ones."""
        path = self.root / "config.json"
        fixed = {k: settings[k] for k in FIXED_SETTINGS}
        if path.is_file():
            import json

            old = json.loads(path.read_text()).get("fixed", {})
            diff = {k: (old.get(k), fixed[k]) for k in FIXED_SETTINGS if old.get(k) != fixed[k]}
            if diff:
                text = "; ".join(f"{k}: {a!r} there, {b!r} now" for k, (a, b) in diff.items())
                raise ConfigError(f"out={self.root} holds a dataset generated with other settings ({text}): use another out= or the same settings")
        else:
            io.write_json(path, {"fixed": fixed})


def dataset_cutoff(outcomes: dict[int, bool], n: int) -> tuple[int | None, int]:
    """(index of the n-th kept index if indices 0..it are all done, else None; first missing index)."""
    kept, i = 0, 0
    while i in outcomes:
        kept += outcomes[i]
        if kept >= n:
            return i, i + 1
        i += 1
    return None, i


def owned_by(item: str, shard: Shard) -> bool:
    """Whether ``shard`` is the only writer of ``item`` (a file stem): its synthetic indices, the backgrounds for
    shard 0, manifest_shard_i for shard i; manifest.json and config.json only when there is one process."""
    if item.startswith(SYN + "_") and item[len(SYN) + 1 :].isdigit():
        return int(item[len(SYN) + 1 :]) % shard.count == shard.index
    if item.startswith(BG + "_"):
        return shard.index == 0
    if item.startswith("manifest_shard_"):
        return item == f"manifest_shard_{shard.index}"
    return shard.count == 1


def kept_below(outcomes: dict[int, bool], j: int) -> int:
    return sum(1 for i, k in outcomes.items() if k and i < j)


# --- generation ---------------------------------------------------------------------------------------------


def settings_from(cfg: DictConfig) -> dict:
    """Checked, resolved settings of a run; raises before any model is built or image rendered."""
    n = cfg.n
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError(f"n={n!r}: expected an integer >= 1 (synthetic images to keep)")
    n_background = cfg.n_background
    if isinstance(n_background, bool) or not isinstance(n_background, int) or n_background < 0:
        raise ConfigError(f"n_background={n_background!r}: expected an integer >= 0")
    shard = Shard.parse(cfg.get("shard"))
    for key in ("min_contrast", "min_background"):
        if not isinstance(cfg[key], (int, float)) or isinstance(cfg[key], bool) or cfg[key] < 0:
            raise ConfigError(f"{key}={cfg[key]!r}: expected a number >= 0")
    if cfg.min_background >= 1:
        raise ConfigError(f"min_background={cfg.min_background}: expected a fraction below 1")
    max_attempts = cfg.get("max_attempts")
    max_attempts = 10 * n + 100 if max_attempts is None else int(max_attempts)
    if max_attempts < n:
        raise ConfigError(f"max_attempts={max_attempts}: expected >= n={n}")
    if cfg.get("out") in (None, ""):
        raise ConfigError("out: expected the dataset folder")

    ckpt_file, run_dir = resolve_checkpoint(cfg.ckpt)
    saved = checkpoint_config(ckpt_file)
    material = str(saved["material"].get("name"))
    wanted = OmegaConf.select(cfg, "material.name")
    if wanted is not None and str(wanted) != material:
        raise ConfigError(f"checkpoint {ckpt_file} was trained for material {material}, not {wanted}")
    contour_px = cfg.get("contour_px")
    contour_px = saved["material"].get("contour_px", 1) if contour_px is None else contour_px
    if isinstance(contour_px, bool) or int(contour_px) != contour_px or contour_px < 0:
        raise ConfigError(f"contour_px={contour_px!r}: expected an integer >= 0")
    renderer = effective_renderer(saved.get("renderer"), cfg.get("renderer"))
    polarity = cfg.get("polarity") or saved["material"].get("polarity", "bright")
    check_polarity(polarity, "polarity" if cfg.get("polarity") else f"the checkpoint's material.polarity")
    backgrounds = cfg.get("backgrounds")
    if backgrounds:
        backgrounds = Path(str(backgrounds)).expanduser().resolve()
        if not backgrounds.is_dir():
            raise ConfigError(f"backgrounds={cfg.backgrounds}: no such folder (expected a PatchSet folder, e.g. <run>/patches)")
    elif run_dir is not None and (run_dir / "patches").is_dir():
        backgrounds = run_dir / "patches"
    else:
        backgrounds = None
    if n_background and backgrounds is None:
        raise ConfigError(f"n_background={n_background}: the checkpoint has no run folder with patches/; give backgrounds=PATCHSET_FOLDER or n_background=0")
    from drgan.build import textured

    if textured(saved["material"]) and backgrounds is None:
        raise ConfigError(
            f"checkpoint {ckpt_file} was trained with material.background_texture, which takes its texture from real "
            "background patches, and it has no run folder with patches/; give backgrounds=PATCHSET_FOLDER"
        )
    return {
        "ckpt": str(ckpt_file),
        "material": material,
        "n": n,
        "n_background": n_background,
        "seed": int(cfg.seed),
        "contour_px": int(contour_px),
        "min_contrast": float(cfg.min_contrast),
        "min_background": float(cfg.min_background),
        "polarity": polarity,
        "max_attempts": max_attempts,
        "renderer": renderer,
        "backgrounds": str(backgrounds) if backgrounds else None,
        "shard": str(shard),
        "model_cfg": {**saved, "renderer": renderer},
    }


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


def render_index(module, sample_phi, settings: dict, index: int):
    """(image, labels, mask, check, meta, render_s, label_s) of index ``index``: reproducible from (seed, index)."""
    seeds = index_seeds(settings["seed"], index)
    phi = sample_phi(seeds["phi"])
    start = time.perf_counter()
    sample = module.generator.sample(phi, seed=seeds["render"])
    render_s = time.perf_counter() - start
    start = time.perf_counter()
    labels = np.asarray(sample.labels)
    mask = class_mask(labels, settings["contour_px"])
    label_s = time.perf_counter() - start
    check = contrast_check(sample.image, labels, settings["min_contrast"], settings["min_background"], settings["polarity"])
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
    return sample.image, labels, mask, check, meta, render_s, label_s


def write_backgrounds(folder: DatasetFolder, settings: dict, resolution: int) -> int:
    todo = [k for k in range(settings["n_background"]) if not folder.done(bg_id(k))]
    if not todo:
        return 0
    path = Path(settings["backgrounds"]) if settings["backgrounds"] else None
    images, sources = load_backgrounds(path, settings["n_background"], resolution)
    for k in todo:
        if k >= len(images):
            break
        zeros = np.zeros(images[k].shape, np.uint8)
        folder.write(bg_id(k), images[k], zeros, zeros, {"kind": "background", "index": k, "source": sources[k]})
    return len(images)


def generate(cfg: DictConfig) -> dict:
    """Render this shard's part of the dataset in ``cfg.out``; return the manifest written (merged or shard)."""
    import torch

    from drgan import build

    settings = settings_from(cfg)
    out = Path(str(cfg.out)).expanduser().resolve()
    folder = DatasetFolder(out)
    shard = Shard.parse(cfg.get("shard"))
    folder.check_settings(settings)
    if cfg.get("merge"):
        return write_manifest(folder, settings, stats=None, required=True)
    folder.remove_partial(lambda item: owned_by(item, shard))

    model_cfg = OmegaConf.create(settings["model_cfg"])
    module = load_module(Path(settings["ckpt"]), settings["model_cfg"])
    if module.textured:
        from drgan.data.patches import PatchSet

        module.use_background_texture(PatchSet.load(settings["backgrounds"]).background)
    resolution = int(module.generator.scene.spec.render.resolution)
    log.info(
        "generating %d images of %s into %s (shard %s, %d x %d px, spp %s, contour %d px)",
        settings["n"], settings["material"], out, shard, resolution, resolution,
        module.generator.scene.spec.render.spp, settings["contour_px"],
    )  # fmt: skip

    def sample_phi(seed: int) -> np.ndarray:
        return build.sample_phi(model_cfg, 1, seed=seed)[0]

    n, stats = settings["n"], Stats()
    if shard.index == 0:
        write_backgrounds(folder, settings, resolution)
    outcomes = folder.outcomes()
    bar = _progress(cfg, total=math.ceil(n / shard.count))
    index = shard.index
    try:
        with torch.no_grad():
            while True:
                if kept_below(outcomes, index) < n and shard.count > 1:
                    outcomes = folder.outcomes()  # what the other shards finished meanwhile
                if kept_below(outcomes, index) >= n:
                    break
                if stats.rendered >= EARLY_ATTEMPTS and stats.kept == 0 and kept_below(outcomes, index) == 0:
                    contrasts = np.asarray(stats.contrasts, dtype=np.float64)
                    median = float(np.nanmedian(contrasts)) if np.isfinite(contrasts).any() else math.nan
                    raise RuntimeError(
                        f"none of the first {stats.rendered} images passed the filter (drop reasons: {dict(stats.reasons)}; "
                        f"median contrast {median:.3f} against min_contrast={settings['min_contrast']} for "
                        f"{settings['polarity']} particles, min_background={settings['min_background']}). A contrast "
                        "below 1 means the particles are on the wrong side of the background: check polarity (here "
                        "from the checkpoint's material) and the epoch (best_epoch.json); or lower min_contrast"
                    )
                if index >= settings["max_attempts"]:
                    have = kept_below(outcomes, index)
                    raise RuntimeError(
                        f"only {have} of n={n} images passed the filter in max_attempts={settings['max_attempts']} "
                        f"indices (drop reasons this run: {dict(stats.reasons) or 'none'}; min_contrast="
                        f"{settings['min_contrast']}, min_background={settings['min_background']}): lower min_contrast "
                        "or min_background, raise max_attempts, or pick a better checkpoint"
                    )
                item = syn_id(index)
                if index in outcomes and (not outcomes[index] or folder.done(item)):
                    stats.skipped += 1
                    index += shard.count
                    continue
                image, labels, mask, check, meta, render_s, label_s = render_index(module, sample_phi, settings, index)
                stats.rendered += 1
                stats.contrasts.append(check.contrast)
                stats.render_s += render_s
                stats.label_s += label_s
                if check.kept:
                    folder.write(item, image, mask, labels, meta)
                    stats.kept += 1
                    bar.update(1)
                else:
                    folder.write_dropped(item, {"reason": check.reason, **meta})
                    stats.dropped += 1
                    stats.reasons[check.reason] += 1
                outcomes[index] = check.kept
                bar.set_postfix(kept=stats.kept, dropped=stats.dropped, skipped=stats.skipped, refresh=False)
                index += shard.count
    finally:
        bar.close()

    summary = stats.as_dict()
    rate = summary["kept_per_minute"]
    print(f"{stats.kept} kept, {stats.dropped} dropped, {stats.skipped} already done; "
          + (f"{rate:.2f} images/minute ({summary['rendered_per_minute']:.2f} rendered/minute)" if rate is not None else "nothing rendered"))  # fmt: skip
    if shard.count > 1:
        write_shard_manifest(folder, settings, shard, summary)
    return write_manifest(folder, settings, stats=summary, required=shard.count == 1)


def _progress(cfg: DictConfig, total: int):
    from tqdm import tqdm

    return tqdm(total=total, desc="kept", unit="img", disable=not cfg.get("progress", True), dynamic_ncols=True)


# --- manifests ----------------------------------------------------------------------------------------------


def public_config(settings: dict) -> dict:
    return {k: v for k, v in settings.items() if k != "model_cfg"}


def write_shard_manifest(folder: DatasetFolder, settings: dict, shard: Shard, stats: dict) -> None:
    outcomes = folder.outcomes()
    mine = sorted(i for i, kept in outcomes.items() if kept and i % shard.count == shard.index)
    io.write_json(folder.root / f"manifest_shard_{shard.index}.json", {
        "shard": str(shard),
        "config": public_config(settings),
        "entries": [{"id": syn_id(i), "kind": "synthetic", "index": i, "files": folder.files(syn_id(i))} for i in mine],
        "throughput": stats,
    })  # fmt: skip


def write_manifest(folder: DatasetFolder, settings: dict, stats: dict | None, required: bool) -> dict:
    """manifest.json of the first n kept indices and the backgrounds, when all are done.

    Incomplete: a ConfigError naming what is missing when ``required`` (single process, merge=true),
    else None (a shard whose siblings are still running)."""
    import json

    outcomes = folder.outcomes()
    cutoff, missing = dataset_cutoff(outcomes, settings["n"])
    backgrounds = [bg_id(k) for k in range(settings["n_background"]) if folder.done(bg_id(k))]
    problem = None
    if cutoff is None:
        problem = f"synthetic index {missing} ({syn_id(missing)}) is not done yet ({kept_below(outcomes, missing)} of n={settings['n']} kept below it)"
    elif len(backgrounds) < settings["n_background"] and settings["n_background"] and not _backgrounds_exhausted(settings, len(backgrounds)):
        problem = f"{len(backgrounds)} of n_background={settings['n_background']} background patches are done (shard 0 writes them)"
    if problem:
        if required:
            raise ConfigError(f"{folder.root}: dataset incomplete: {problem}; run the shards (same command, without merge=true)")
        log.info("manifest.json not written yet: %s", problem)
        return None
    kept = [i for i in range(cutoff + 1) if outcomes[i]]
    dropped = [i for i in range(cutoff + 1) if not outcomes[i]]
    reasons: Counter = Counter()
    for i in dropped:
        try:
            reasons[json.loads((folder.root / "dropped" / f"{syn_id(i)}.json").read_text()).get("reason")] += 1
        except (OSError, ValueError):
            reasons["unknown"] += 1
    entries = [{"id": syn_id(i), "kind": "synthetic", "index": i, "files": folder.files(syn_id(i))} for i in kept]
    entries += [{"id": b, "kind": "background", "files": folder.files(b)} for b in backgrounds]
    shards = []
    for path in sorted(folder.root.glob("manifest_shard_*.json")):
        record = json.loads(path.read_text())
        if record.get("config", {}).get("ckpt") == settings["ckpt"]:
            shards.append({"shard": record.get("shard"), **record.get("throughput", {})})
    surplus = sum(1 for i, k in outcomes.items() if k and i > cutoff)
    manifest = {
        "config": {**public_config(settings), "shard": None},
        "counts": {
            "synthetic": len(kept),
            "background": len(backgrounds),
            "kept": len(kept),
            "dropped": len(dropped),
            "drop_reasons": dict(reasons),
            "attempted": cutoff + 1,
            "surplus_kept_not_listed": surplus,
        },
        "throughput": {"this_run": stats, "shards": shards},
        "entries": entries,
    }
    io.write_json(folder.root / "manifest.json", manifest)
    log.info("manifest.json: %d synthetic (%d dropped) + %d background", len(kept), len(dropped), len(backgrounds))
    return manifest


def _backgrounds_exhausted(settings: dict, done: int) -> bool:
    """True when the PatchSet holds fewer background patches than asked for and all of them are done."""
    if not settings["backgrounds"]:
        return False
    from drgan.data.patches import PatchSet

    try:
        return done >= len(PatchSet.load(settings["backgrounds"]).background)
    except DataError:
        return False


@hydra.main(version_base="1.3", config_path="../../conf", config_name="generate")
def main(cfg: DictConfig) -> None:
    generate(cfg)


if __name__ == "__main__":
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    main()
