"""`python -m drgan.realism data.dir=DIR synthetic=SOURCE`: can a small CNN tell synthetic patches from real ones?

A classifier two-sample test (drgan.metrics.two_sample): real training patches (the split's train ids only,
mined exactly as drgan.train mines them: drgan.data.datamodule.RealPatchDataModule with the same data.* settings)
against a synthetic source, balanced, k-fold cross-validated, each patch predicted by a network that never
trained on it. Accuracy near 0.5 = indistinguishable; near 1 = the CNN sees the difference. With its 95 %
interval, a one-sided binomial p-value against 0.5, and the AUC.

synthetic=
- ``real``: real against real: the train images split in two halves by image id (seeded), so that one image's
  patches stay in one half; the calibration of the test (expected 0.5 within its interval);
- a drgan.generate dataset folder (manifest.json): its synthetic images (the real background patches that
  generate adds are left out), a seeded random choice of n;
- a generator checkpoint (.ckpt) or training run folder (its checkpoints/best.ckpt): n renders with the FID
  callback's ``render_samples`` (the phi bank of the checkpoint, seeds of their own), rounded to 8 bits like the
  real images and generate's PNGs (render.quantize);
- any other folder: its images (TIFF / PNG / JPEG), each one patch.

In either case a real image's patches share a cross-validation fold (a network must not score by recognising an
image whose other patches it trained on). Writes, in ``out``: results.json (everything) and results.md (one
table line, also printed). Real patches are cached in data.cache_dir (default out/patches, with a contact sheet
of real patches: keep it out of repositories).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from drgan.core.errors import ConfigError, DataError, check_keys
from drgan.core.io import write_bytes, write_json
from drgan.core.typed_settings import read_settings, setting, typed
from drgan.launch.runtime import stage_main, start
from drgan.metrics.two_sample import ClassifierSettings, two_sample_test

log = logging.getLogger(__name__)

# Renders for the test use seeds of their own, apart from training's and the FID callback's (0x5EED0000 + ...).
REALISM_SEED_BASE = 0x7EA10000
HEADER = "| source | patches per class | accuracy [95 % CI] | p (vs 0.5) | AUC | FID |\n|---|---|---|---|---|---|"


# --- the real patches -------------------------------------------------------------------------------------------


def data_keys(stage: str, data) -> dict:
    """``data``: the RealPatchDataModule's keys (dir required), checked before any image is read."""
    data = dict(data or {})
    if not data.get("dir"):
        raise ConfigError(
            f"{stage}: give data.dir=DIR (the folder of real images; its split.json's train ids are read)"
        )
    allowed = {
        "dir",
        "split",
        "crop_rows",
        "patch_size",
        "stride",
        "min_particles",
        "n_background",
        "background_stride",
        "segment",
        "cache_dir",
        "polarity",
    }
    check_keys("data", data, sorted(allowed), "setting")
    return data


def real_patches(data: dict):
    """The RealPatchDataModule of the ``data`` keys, set up: its mined patches (train ids only) and ids."""
    from drgan.data.datamodule import RealPatchDataModule

    module = RealPatchDataModule(**data, augment=False, check_material=False)
    module.setup()
    patches = module.patches
    if set(patches.train_ids) & set(module.test_ids):  # RealPatchDataModule refuses this already; the rule is ours too
        raise DataError("realism: a test image's patches reached the real sample")
    log.info(
        "real: %d patches of %d px from %d train images of %s (polarity %s)",
        len(patches.train),
        module.patch_size,
        len(set(patches.train_ids)),
        module.dir,
        module.polarity,
    )
    return module


# --- the synthetic source ---------------------------------------------------------------------------------------


def source_kind(source) -> str:
    """What ``synthetic=`` names: real, dataset, checkpoint or images (a ConfigError for anything else)."""
    from drgan.synthetic import is_generated

    if source is None or str(source) in ("", "???", "None", "null"):
        raise ConfigError(
            "realism: give synthetic=real, a drgan.generate dataset folder, a generator checkpoint "
            "(.ckpt) or training run folder, or a folder of images"
        )
    if str(source) == "real":
        return "real"
    path = Path(str(source)).expanduser()
    if path.is_file():
        if path.suffix != ".ckpt":
            raise ConfigError(
                f"synthetic={source}: a file that is not a .ckpt (expected a generator checkpoint, a "
                "dataset folder, a folder of images or real)"
            )
        return "checkpoint"
    if not path.is_dir():
        raise ConfigError(
            f"synthetic={source}: no such file or folder (expected real, a drgan.generate dataset "
            "folder, a generator checkpoint or training run folder, or a folder of images)"
        )
    if is_generated(path):
        return "dataset"
    if (path / "checkpoints" / "best.ckpt").is_file():
        return "checkpoint"
    return "images"


def dataset_images(folder: Path, n: int, seed: int) -> tuple[np.ndarray, list[str]]:
    """n synthetic images of a drgan.generate dataset, a seeded random choice (all of them when it has fewer)."""
    from drgan.synthetic import SYNTHETIC, check_files, manifest_entries, read_manifest

    entries = [e for e in manifest_entries(read_manifest(folder, "synthetic")) if e.kind == SYNTHETIC]
    if not entries:
        raise DataError(f"synthetic={folder}: the dataset lists no synthetic images (only real backgrounds)")
    chosen = sorted(np.random.default_rng(seed).choice(len(entries), min(n, len(entries)), replace=False))
    entries = [entries[i] for i in chosen]
    check_files(folder, entries, ("image",), "synthetic")
    return _read_all([folder / e.files["image"] for e in entries], "synthetic"), [e.id for e in entries]


def folder_images(folder: Path, n: int, seed: int) -> tuple[np.ndarray, list[str]]:
    from drgan.data.images import list_images

    paths = list_images(folder)
    chosen = sorted(np.random.default_rng(seed).choice(len(paths), min(n, len(paths)), replace=False))
    paths = [paths[i] for i in chosen]
    return _read_all(paths, "synthetic"), [p.stem for p in paths]


def _read_all(paths: list[Path], setting: str) -> np.ndarray:
    from tqdm.auto import tqdm

    from drgan.data.images import read_grey

    images = [read_grey(p) for p in tqdm(paths, desc="reading synthetic images", unit="image", leave=False)]
    shapes = sorted({im.shape for im in images})
    if len(shapes) > 1:
        raise DataError(
            f"{setting}: images of several sizes {shapes[:3]} (expected one size, that of the real patches)"
        )
    return np.stack(images).astype(np.float32)


def checkpoint_renders(
    source, n: int, background: np.ndarray, size: int, spp: int | None, quantize: bool, parameters="trained"
) -> tuple[np.ndarray, dict]:
    """n renders of a generator checkpoint with the FID callback's render_samples; (images, what rendered them).
    size: the real patches' size, which the checkpoint's resolution must equal (checked before rendering);
    parameters: the scene values (`drgan.synthetic.generation_settings.parameter_source`: trained, initial, middle,
    a mapping)."""
    import torch

    from drgan.callbacks.fid import render_samples
    from drgan.synthetic.generation_settings import parameter_source
    from drgan.synthetic.source import checkpoint_config, generator_checkpoint, load_module, use_parameters

    parameters = parameter_source(parameters)
    ckpt_file, _ = generator_checkpoint(source)
    model_cfg = checkpoint_config(ckpt_file)
    module = load_module(ckpt_file, model_cfg)
    use_parameters(module, parameters, model_cfg)
    if module.textured:
        module.use_background_texture(background)
    render = module.generator.scene.spec.render
    if int(render.resolution) != size:
        raise DataError(
            f"synthetic={source}: the checkpoint renders {render.resolution} px images, but the real "
            f"patches are {size} px (data.patch_size): the test compares them at one size"
        )
    if len(module.phi_bank) == 0:
        raise ConfigError(f"synthetic={source}: the checkpoint has no constellations (phi bank) to render")
    with torch.no_grad():
        images = render_samples(module, n, REALISM_SEED_BASE, progress=True, spp=spp)
    if quantize:  # the real images are 8 bit, and so are generate's PNGs: a fine-grained tell otherwise
        images = np.round(images * 255.0) / 255.0
    return images.astype(np.float32), {
        "ckpt": str(ckpt_file),
        "material": model_cfg["material"].get("name"),
        "resolution": int(render.resolution),
        "spp": spp or int(render.spp),
        "seed_base": REALISM_SEED_BASE,
        "quantized_8bit": bool(quantize),
        "parameters": parameters,
    }


def real_halves(ids: list[str], seed: int) -> tuple[set[str], set[str]]:
    """The image ids split in two halves of equal count (the first one smaller by one for an odd count)."""
    unique = sorted(set(ids))
    if len(unique) < 2:
        raise DataError(f"realism: synthetic=real needs patches from at least 2 images (got {len(unique)})")
    order = np.random.default_rng(seed).permutation(len(unique))
    half = len(unique) // 2
    return {unique[i] for i in order[:half]}, {unique[i] for i in order[half:]}


# --- the test ---------------------------------------------------------------------------------------------------


def classifier_settings(test, seed: int) -> ClassifierSettings:
    """``test``: the classifier's keys (drgan.metrics.two_sample.ClassifierSettings), checked; ``seed`` the run's."""
    test = dict(test or {})
    allowed = set(ClassifierSettings.__dataclass_fields__) - {"seed"}
    check_keys("test", test, sorted(allowed), "setting")
    try:
        test = {k: float(v) if k in ("lr", "weight_decay") else v for k, v in test.items()}
    except (TypeError, ValueError):
        raise ConfigError(f"realism: test.lr / test.weight_decay: expected numbers (got {test})") from None
    settings = ClassifierSettings(**test, seed=seed)
    settings.check()
    return settings


@typed
@dataclass(frozen=True)
class RenderKeys:
    """``render``: how a checkpoint's images are rendered for the test (synthetic=CHECKPOINT only)."""

    spp: int | None = setting(None, ge=1)  # null: the checkpoint's training spp
    parameters: Any = "trained"  # trained | initial | middle | {key: value, ...} (as drgan.generate's)
    quantize: bool = True


@typed
@dataclass(frozen=True)
class RealismSettings:
    """Every key of conf/gan/realism.yaml, typed and checked (`read_settings`) before any image is read."""

    synthetic: str = setting(check=lambda stage, source: source if source is None else str(source))  # `source_kind`
    out: Path = setting()
    data: dict = setting(check=data_keys)
    n_synthetic: int | None = setting(None, ge=2)
    render: RenderKeys = setting(
        RenderKeys(), check=lambda stage, node: read_settings(RenderKeys, node or {}, stage, prefix="render.")
    )
    test: dict = field(default_factory=dict)  # the classifier's keys (`classifier`)
    fid: bool = True
    seed: int = setting(0, ge=0)
    threads: int | None = setting(1, ge=1)
    progress: bool = True
    kind: str = field(default="", init=False)  # what synthetic names (`source_kind`)
    classifier: ClassifierSettings | None = field(default=None, init=False)  # the test's keys, checked

    def __post_init__(self):
        """The source's kind and the classifier's keys resolved once, before any patch is mined (frozen: set here)."""
        object.__setattr__(self, "kind", source_kind(self.synthetic))
        object.__setattr__(self, "classifier", classifier_settings(self.test, self.seed))

    @classmethod
    def from_config(cls, cfg: DictConfig) -> RealismSettings:
        return read_settings(cls, cfg, "realism")


def realism(s: RealismSettings) -> dict:
    """Run the two-sample test of ``synthetic`` against the real train patches of ``data``; write the results."""
    import torch

    settings = s.classifier
    kind = s.kind
    n_wanted, spp = s.n_synthetic, s.render.spp
    if s.threads is not None:
        torch.set_num_threads(s.threads)
    seed = settings.seed

    module = real_patches(s.data)
    patches = module.patches
    real, real_ids = patches.train, list(patches.train_ids)
    size = real.shape[1]
    if len(real) < 2 * settings.folds:
        raise DataError(
            f"realism: only {len(real)} real patches from data.dir={module.dir}; {settings.folds} folds "
            f"need at least {2 * settings.folds}: lower data.stride or data.min_particles, or test.folds"
        )
    n = n_wanted or len(real)
    source = s.synthetic
    if kind == "real":
        a, b, groups_a, groups_b, label, detail = _real_halves(real, real_ids, seed)
    else:
        b, groups_b, label, detail = _synthetic_sample(s.render, kind, source, n, seed, patches.background, size, spp)
        a, groups_a = real, real_ids
    log.info("two-sample test: %s: %d patches (A) against %d (B), %d px", label, len(a), len(b), size)
    result = two_sample_test(a, b, settings, groups_a, groups_b, progress=s.progress)
    if s.fid:
        result.update(sample_fid(a, b))
    line = markdown_line(label, result)
    out = s.out
    summary = {
        "source": {"synthetic": source, "kind": kind, "label": label, **detail},
        "real": {
            "dir": str(module.dir.resolve()),
            "train_ids": module.train_ids,
            "patches": len(real),
            "patch_size": size,
            "polarity": module.polarity,
            "data": s.data,
        },
        "test": result,
        "markdown": line,
        "out": str(out.resolve()),
    }
    write_json(out / "results.json", summary)
    write_bytes(out / "results.md", f"{HEADER}\n{line}\n".encode())
    print(f"{HEADER}\n{line}")
    log.info("wrote %s", out / "results.json")
    return summary


def _real_halves(real: np.ndarray, real_ids: list, seed: int):
    """(A, B, their groups, label, detail): the real train patches in two halves by image id (the test's floor)."""
    first, second = real_halves(real_ids, seed)
    in_first = np.array([i in first for i in real_ids])
    a, groups_a = real[in_first], [i for i, keep in zip(real_ids, in_first) if keep]
    b, groups_b = real[~in_first], [i for i, keep in zip(real_ids, in_first) if not keep]
    label = "real vs real (train images in two halves by id)"
    return a, b, groups_a, groups_b, label, {"half_a_ids": sorted(first), "half_b_ids": sorted(second)}


def _synthetic_sample(render: RenderKeys, kind: str, source: str, n: int, seed: int, background, size: int, spp):
    """(images, their names, label, detail): ``n`` images of a generated dataset, a folder of images, or renders of
    a checkpoint, at the real patches' size (a DataError otherwise)."""
    detail: dict = {}
    if kind == "dataset":
        b, names = dataset_images(Path(source), n, seed)
        label = f"dataset {source}"
    elif kind == "images":
        b, names = folder_images(Path(source), n, seed)
        label = f"images {source}"
    else:
        quantize, parameters = render.quantize, render.parameters
        b, detail = checkpoint_renders(source, n, background, size, spp, quantize, parameters)
        names = [f"render_{i}" for i in range(len(b))]
        chosen = detail["parameters"]
        label = f"renders of {source}" + (
            "" if chosen == "trained" else f" ({chosen if isinstance(chosen, str) else 'fixed'} values)"
        )
    if b.shape[1:] != (size, size):
        raise DataError(
            f"synthetic={source}: images of {b.shape[2]} x {b.shape[1]} px, but the real patches are "
            f"{size} x {size} px (data.patch_size): the test compares them at one size"
        )
    detail["synthetic_read"] = len(b)
    return b, names, label, detail


def sample_fid(a: np.ndarray, b: np.ndarray) -> dict:
    """FID and KID (clean-fid's Inception features, `drgan.metrics.feature_distances`) of the two whole samples of the
    test: what the training's FID would say about them, beside the classifier's accuracy."""
    from drgan.metrics.feature_distances import FeatureStats, kid
    from drgan.metrics.inception import InceptionFeatures

    extractor = InceptionFeatures()
    fa, fb = extractor.features(a), extractor.features(b)
    kid_mean, _ = kid(fb, fa)
    return {"fid": FeatureStats.from_features(fb).fid(FeatureStats.from_features(fa)), "kid": float(kid_mean)}


def markdown_line(label: str, result: dict) -> str:
    low, high = result["interval"]
    fid = f" {result['fid']:.1f} |" if "fid" in result else " - |"
    return (
        f"| {label} | {result['n_per_class']} | {result['accuracy']:.3f} [{low:.3f}, {high:.3f}] | "
        f"{result['p_value']:.2g} | {result['auc']:.3f} |{fid}"
    )


@stage_main("conf/gan", "realism")
def main(cfg: DictConfig):
    realism(RealismSettings.from_config(cfg))


if __name__ == "__main__":
    start(main)
