"""The settings of a generation run, checked and resolved against the checkpoint before anything is built.

``FIXED_SETTINGS`` decide what each index holds: config.json records them at a folder's first use, and a folder
is only ever completed with the same ones (n and n_background may grow). The rest (n, max_attempts, shard)
only decide how much is made and by whom. The partial-background settings (``PARTIAL_SETTINGS``) decide what the
pbg_ items hold; like ``parameters`` they are recorded only when not the defaults, so that folders made before
they existed still resume (and then fill up with the default partial backgrounds, as a new folder would).
"""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from drgan.data.polarity import check_polarity
from drgan.errors import ConfigError
from drgan.scene.config import typed_material
from drgan.synthetic.backgrounds import PARTIAL_MAX_IGNORED
from drgan.synthetic.shards import Shard
from drgan.synthetic.source import checkpoint_config, effective_renderer, generator_checkpoint

log = logging.getLogger(__name__)

FIXED_SETTINGS = (
    "ckpt",
    "material",
    "seed",
    "contour_px",
    "min_contrast",
    "min_background",
    "polarity",
    "renderer",
    "backgrounds",
)


# The partial-background settings and their defaults (conf/gan/generate.yaml).
PARTIAL_SETTINGS = {"partial_background": True, "partial_max_ignored": PARTIAL_MAX_IGNORED, "partial_margin_px": None}
# Settings recorded only when not at their default, so that folders made before them still resume.
OPTIONAL_SETTINGS = {**PARTIAL_SETTINGS, "grey_spread": False}


def fixed_settings(settings: dict) -> dict:
    """The part of ``settings`` that config.json records and every later run must repeat (``parameters`` and the
    partial-background settings only when not the defaults, so that folders made before them still resume)."""
    fixed = {k: settings[k] for k in FIXED_SETTINGS}
    if settings.get("parameters", "trained") != "trained":
        fixed["parameters"] = settings["parameters"]
    for key, default in OPTIONAL_SETTINGS.items():
        if settings.get(key, default) != default:
            fixed[key] = settings[key]
    return fixed


def partial_settings(cfg: DictConfig) -> dict:
    """partial_background (bool), partial_max_ignored (a fraction in [0, 1]), partial_margin_px (an integer >= 0
    or null), checked."""
    enabled = cfg.get("partial_background", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"partial_background={enabled!r}: expected true or false")
    max_ignored = cfg.get("partial_max_ignored", PARTIAL_MAX_IGNORED)
    if isinstance(max_ignored, bool) or not isinstance(max_ignored, (int, float)) or not 0 <= max_ignored <= 1:
        raise ConfigError(f"partial_max_ignored={max_ignored!r}: expected a fraction in [0, 1]")
    margin = cfg.get("partial_margin_px")
    if margin is not None and (isinstance(margin, bool) or not isinstance(margin, int) or margin < 0):
        raise ConfigError(f"partial_margin_px={margin!r}: expected an integer >= 0 (px) or null (from the particles)")
    return {"partial_background": enabled, "partial_max_ignored": float(max_ignored), "partial_margin_px": margin}


def settings_from(cfg: DictConfig) -> dict:
    """Checked, resolved settings of a run (conf/gan/generate.yaml); raises before any model is built or image rendered.

    Keys (in the order manifests record them): ckpt, material, n, n_background, partial_background,
    partial_max_ignored, partial_margin_px, seed, contour_px, min_contrast, min_background, polarity, max_attempts,
    renderer, backgrounds, shard, parameters, and model_cfg (the checkpoint's config
    with the effective renderer, which is not recorded)."""
    n = cfg.n
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError(f"n={n!r}: expected an integer >= 1 (synthetic images to keep)")
    n_background = cfg.n_background
    if isinstance(n_background, bool) or not isinstance(n_background, int) or n_background < 0:
        raise ConfigError(f"n_background={n_background!r}: expected an integer >= 0")
    partial = partial_settings(cfg)
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

    ckpt_file, run_dir = generator_checkpoint(cfg.ckpt)
    saved = checkpoint_config(ckpt_file)
    typed = typed_material(saved["material"])
    material = typed.name
    wanted = OmegaConf.select(cfg, "material.name")
    if wanted is not None and str(wanted) != material:
        raise ConfigError(f"checkpoint {ckpt_file} was trained for material {material}, not {wanted}")
    contour_px = cfg.get("contour_px")
    contour_px = typed.contour_px if contour_px is None else contour_px
    if isinstance(contour_px, bool) or int(contour_px) != contour_px or contour_px < 0:
        raise ConfigError(f"contour_px={contour_px!r}: expected an integer >= 0")
    renderer = effective_renderer(saved.get("renderer"), cfg.get("renderer"))
    polarity = cfg.get("polarity") or typed.polarity
    check_polarity(polarity, "polarity" if cfg.get("polarity") else "the checkpoint's material.polarity")
    backgrounds = background_source(cfg.get("backgrounds"), run_dir)
    if n_background and backgrounds is None:
        raise ConfigError(
            f"n_background={n_background}: the checkpoint has no run folder with patches/; "
            "give backgrounds=PATCHSET_FOLDER or n_background=0"
        )
    if typed.background_texture.enabled and backgrounds is None:
        raise ConfigError(
            f"checkpoint {ckpt_file} was trained with material.background_texture, which takes its texture from real "
            "background patches, and it has no run folder with patches/; give backgrounds=PATCHSET_FOLDER"
        )
    grey_spread = cfg.get("grey_spread", False)
    if grey_spread == "auto":  # on wherever real train patches are at hand (every drgan.train run has them)
        grey_spread = backgrounds is not None
        if not grey_spread:
            log.info("grey_spread=auto: off, the checkpoint has no run folder with real patches (backgrounds=...)")
    if not isinstance(grey_spread, bool):
        raise ConfigError(f"grey_spread={grey_spread!r}: expected auto, true or false")
    if grey_spread and backgrounds is None:
        raise ConfigError(
            "grey_spread=true draws each image's grey levels from the real train patches, and the checkpoint has no "
            "run folder with patches/; give backgrounds=PATCHSET_FOLDER or grey_spread=false"
        )
    return {
        "ckpt": str(ckpt_file),
        "grey_spread": grey_spread,
        "material": material,
        "n": n,
        "n_background": n_background,
        **partial,
        "seed": int(cfg.seed),
        "contour_px": int(contour_px),
        "min_contrast": float(cfg.min_contrast),
        "min_background": float(cfg.min_background),
        "polarity": polarity,
        "max_attempts": max_attempts,
        "renderer": renderer,
        "backgrounds": str(backgrounds) if backgrounds else None,
        "shard": str(shard),
        "parameters": parameter_source(cfg.get("parameters", "trained")),
        "model_cfg": {**saved, "renderer": renderer},
    }


PARAMETER_SOURCES = ("trained", "initial", "middle")


def parameter_source(given) -> str | dict:
    """``parameters=``: where each image's scene values come from (the ablations of experiments/tio2_sem/ABLATION.md):
    "trained" (the generator's network, default), "initial" (the same network at its initial weights, before any
    training step), "middle" (every learned parameter at the middle of its limits), or a mapping {key: value} of
    every learned parameter (e.g. ``parameters={particle.roughness: 0.5, ...}``), the same for every image."""
    if isinstance(given, DictConfig):
        given = OmegaConf.to_container(given, resolve=True)
    if isinstance(given, str) and given in PARAMETER_SOURCES:
        return given
    if isinstance(given, dict) and given:
        values = {}
        for key, value in _flatten(given).items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"parameters.{key}={value!r}: expected a number")
            values[str(key)] = float(value)
        return dict(sorted(values.items()))
    raise ConfigError(
        f"parameters={given!r}: expected one of {', '.join(PARAMETER_SOURCES)} or a mapping of every learned "
        "parameter to a value, e.g. parameters={particle.roughness: 0.5, ...}"
    )


def background_source(given, run_dir: Path | None) -> Path | None:
    """The PatchSet folder of the background items: ``backgrounds=`` when given, else <run folder>/patches."""
    if given:
        path = Path(str(given)).expanduser().resolve()
        if not path.is_dir():
            raise ConfigError(f"backgrounds={given}: no such folder (expected a PatchSet folder, e.g. <run>/patches)")
        return path
    if run_dir is not None and (run_dir / "patches").is_dir():
        return run_dir / "patches"
    return None


def _flatten(mapping: dict, prefix: str = "") -> dict:
    """{particle: {roughness: 0.5}} -> {"particle.roughness": 0.5} (YAML nesting or dotted keys alike)."""
    flat = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat
