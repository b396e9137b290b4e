"""The settings of a generation run: `GenerateSettings`, one frozen dataclass holding every key of
conf/gan/generate.yaml with its type, its default and its check, resolved against the checkpoint before anything
is built.

The YAML stays the user's reference (what each key means, its unit and range); the field defaults are the same values
(tests/test_generate.py composes generate.yaml and compares). A new key is a field here, with its check in
``__post_init__`` where a value can be wrong, and, where users should see it, its line in the YAML; the stage reads
it as ``settings.KEY``, and manifest.json records it.

What each setting is recorded as (field metadata, set with `setting`):

- manifest.json's "config" records every setting but out, merge and progress (``record=False``), resolved, in field
  order (the order manifests have always had);
- config.json's "fixed" records the settings that decide what each index holds: written at a folder's first use, a
  folder is only ever completed with the same ones. ``fixed=ALWAYS``: recorded always; ``fixed=NEVER``: n,
  n_background, max_attempts and shard only decide how much is made and by whom (n and n_background may grow); any
  other setting (a new one too, ``fixed=CHANGED``) is recorded only when it is not at its ``before`` value, the value
  that folders made before the key existed were made with (the field's default unless given): such folders resume,
  and a run that asks for something else is refused.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, NamedTuple

from omegaconf import MISSING, DictConfig, OmegaConf

from drgan.core.errors import ConfigError
from drgan.core.typed_settings import checks, read_settings
from drgan.data.polarity import check_polarity
from drgan.scene.config import Material, typed_material
from drgan.synthetic.backgrounds import PARTIAL_MAX_IGNORED, PartialSettings
from drgan.synthetic.shards import Shard
from drgan.synthetic.source import checkpoint_config, effective_renderer, generator_checkpoint

log = logging.getLogger(__name__)

ALWAYS, NEVER, CHANGED = "always", "never", "changed"  # config.json records a setting: always, never, when changed
# config.json lists the settings it records when changed in the order they were added to drgan; a new one follows.
_CHANGED_ORDER = (
    "parameters",
    "partial_background",
    "partial_max_ignored",
    "partial_margin_px",
    "grey_spread",
    "size",
    "placement",
)
_DEFAULT = object()


def setting(
    default: Any = _DEFAULT,
    *,
    fixed: str = CHANGED,
    record: bool = True,
    before: Any = _DEFAULT,
    factory=None,
    given=None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    expected: str | None = None,
):
    """A field of `GenerateSettings`: its ``default`` (or ``factory`` for a mutable one), whether config.json records
    it (``fixed``: ALWAYS, NEVER, or CHANGED from ``before``), whether manifest.json does (``record``), ``given``
    (cfg -> value) where the value is not the composed config's key of the field's name, and what
    `drgan.core.typed_settings.read_settings` checks when it reads the key, as for every stage's settings: bounds
    (``ge``, ``gt``, ``le``) and ``expected``, the words of the error (else derived from the type and the bounds).
    ``__post_init__`` checks what a bound cannot say (and a value given to the constructor directly)."""
    if fixed not in (ALWAYS, NEVER, CHANGED):
        raise ValueError(f"fixed={fixed!r}: expected ALWAYS, NEVER or CHANGED")
    metadata: dict[str, Any] = {"fixed": fixed, "record": record, **checks(ge=ge, gt=gt, le=le, expected=expected)}
    if before is not _DEFAULT:
        metadata["before"] = before
    if given is not None:
        metadata["given"] = given
    if factory is not None:
        return field(default_factory=factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def _material_name(cfg: DictConfig):
    """``material=NAME`` on generate's command line: only checked against the checkpoint's material."""
    return OmegaConf.select(cfg, "material.name")


def _layout_group(group: str):
    """Reader of ``size=NAME`` / ``placement=NAME`` (and their keys) on generate's command line: the group as a plain
    dict, unresolved (its ``${material.*}`` are the checkpoint's material's: `GenerateSettings.resolve`), or None when
    not given (the checkpoint's)."""

    def given(cfg: DictConfig):
        value = cfg.get(group)
        value = OmegaConf.to_container(value, resolve=False) if isinstance(value, DictConfig) else value
        return dict(value) if value else None

    return given


def _renderer_overrides(cfg: DictConfig) -> dict:
    """generate's ``renderer.KEY=VALUE``: the keys that replace the checkpoint's (null: the checkpoint's)."""
    given = cfg.get("renderer")
    given = OmegaConf.to_container(given, resolve=True) if isinstance(given, DictConfig) else dict(given or {})
    return {k: v for k, v in given.items() if v is not None}


# Fields in the order manifest.json's "config" records them; what each means: conf/gan/generate.yaml.
@dataclass(frozen=True, kw_only=True)
class GenerateSettings:
    """The settings of ``python -m drgan.generate`` (conf/gan/generate.yaml), each checked on construction (a
    ConfigError naming the key and what was expected). Built from the composed config by `from_config`; `resolve`
    replaces the nulls that mean "the checkpoint's" (ckpt's file, material, contour_px, polarity, renderer,
    backgrounds, grey_spread=auto) before any model is built or image rendered."""

    ckpt: str = setting(MISSING, fixed=ALWAYS)  # resolved: the checkpoint file
    grey_spread: bool | str = setting("auto", before=False)  # auto | true | false; resolved: true or false
    material: str | None = setting(None, fixed=ALWAYS, given=_material_name)  # resolved: the checkpoint's material
    n: int = setting(1000, fixed=NEVER)
    n_background: int = setting(200, fixed=NEVER)
    partial_background: bool = setting(True)
    partial_max_ignored: float = setting(PARTIAL_MAX_IGNORED)
    partial_margin_px: int | None = setting(None, expected="an integer >= 0 (px) or null (from the particles)")
    seed: int = setting(0, fixed=ALWAYS)
    contour_px: int | None = setting(None, fixed=ALWAYS, expected="an integer >= 0 or null (the checkpoint material's)")
    min_contrast: float = setting(1.15, fixed=ALWAYS)
    min_background: float = setting(0.05, fixed=ALWAYS)
    polarity: str | None = setting(None, fixed=ALWAYS)  # resolved: the checkpoint material's when null
    max_attempts: int | None = setting(None, fixed=NEVER)  # null: 10 * n + 100 (on construction)
    renderer: dict = setting(factory=dict, fixed=ALWAYS, given=_renderer_overrides)  # resolved: the effective one
    sampled_spp: int | None = setting(None)  # replaces renderer.spp for a material whose renders carry sampling noise
    backgrounds: str | None = setting(None, fixed=ALWAYS)  # resolved: <run folder>/patches when null and there
    shard: str | None = setting(None, fixed=NEVER)  # "i/k" on construction (null: "0/1")
    parameters: str | dict = setting("trained")  # trained | initial | middle | {key: value}
    # The constellations: the checkpoint's size distribution and placement, or the ones given (the generator maps any
    # constellation to its scene; a folder is only completed with the same ones)
    size: dict | None = setting(None, given=_layout_group("size"))
    placement: dict | None = setting(None, given=_layout_group("placement"))
    out: str = setting(MISSING, fixed=NEVER, record=False)
    merge: bool = setting(False, fixed=NEVER, record=False)
    progress: bool = setting(True, fixed=NEVER, record=False)

    def __post_init__(self):
        """Check every value on its own (the checks that need the checkpoint are `resolve`'s) and normalise it:
        numbers to int or float, max_attempts' null to 10 * n + 100, shard to "i/k", parameters as
        `parameter_source` gives them."""
        _count("n", self.n, 1, " (synthetic images to keep)")
        _count("n_background", self.n_background, 0)
        if not isinstance(self.partial_background, bool):
            raise ConfigError(f"partial_background={self.partial_background!r}: expected true or false")
        max_ignored = self.partial_max_ignored
        if isinstance(max_ignored, bool) or not isinstance(max_ignored, (int, float)) or not 0 <= max_ignored <= 1:
            raise ConfigError(f"partial_max_ignored={max_ignored!r}: expected a fraction in [0, 1]")
        margin = self.partial_margin_px
        if margin is not None and (isinstance(margin, bool) or not isinstance(margin, int) or margin < 0):
            raise ConfigError(
                f"partial_margin_px={margin!r}: expected an integer >= 0 (px) or null (from the particles)"
            )
        shard = str(Shard.parse(self.shard))
        for key in ("min_contrast", "min_background"):
            value = getattr(self, key)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value < 0:
                raise ConfigError(f"{key}={value!r}: expected a number >= 0")
        if self.min_background >= 1:
            raise ConfigError(f"min_background={self.min_background}: expected a fraction below 1")
        max_attempts = 10 * self.n + 100 if self.max_attempts is None else _integer("max_attempts", self.max_attempts)
        if max_attempts < self.n:
            raise ConfigError(f"max_attempts={max_attempts}: expected >= n={self.n}")
        if self.out in (None, "", MISSING):
            raise ConfigError("out: expected the dataset folder")
        contour_px = self.contour_px
        if contour_px is not None:
            try:
                whole = not isinstance(contour_px, bool) and int(contour_px) == contour_px and contour_px >= 0
            except (TypeError, ValueError):
                whole = False
            if not whole:
                raise ConfigError(f"contour_px={contour_px!r}: expected an integer >= 0")
            contour_px = int(contour_px)
        if self.polarity:
            check_polarity(self.polarity, "polarity")
        if self.sampled_spp is not None:
            _count("sampled_spp", self.sampled_spp, 1, " (samples per pixel) or null")
        if self.grey_spread != "auto" and not isinstance(self.grey_spread, bool):
            raise ConfigError(f"grey_spread={self.grey_spread!r}: expected auto, true or false")
        normal = {
            "partial_max_ignored": float(max_ignored),
            "shard": shard,
            "seed": _integer("seed", self.seed),
            "contour_px": contour_px,
            "min_contrast": float(self.min_contrast),
            "min_background": float(self.min_background),
            "polarity": self.polarity or None,
            "max_attempts": max_attempts,
            "parameters": parameter_source(self.parameters),
        }
        for key, value in normal.items():
            object.__setattr__(self, key, value)

    @classmethod
    def from_config(cls, cfg: DictConfig) -> GenerateSettings:
        """The settings of a composed generate config, read as every stage's are
        (`drgan.core.typed_settings.read_settings`: each key of a field's name against the field's type; a key ``cfg``
        lacks takes the field's default), the fields with a ``given`` reader by it; then checked (``__post_init__``)."""
        given = {f.name: f.metadata["given"](cfg) for f in fields(cls) if "given" in f.metadata}
        return read_settings(cls, cfg, "generate", **given)

    def resolve(self) -> Resolved:
        """These settings with every "the checkpoint's" filled in from the checkpoint, and the model config to
        render with (the checkpoint's, with the effective renderer); raises before any model is built."""
        ckpt_file, run_dir = generator_checkpoint(self.ckpt)
        saved = checkpoint_config(ckpt_file)
        typed = typed_material(saved["material"])
        if self.material is not None and str(self.material) != typed.name:
            raise ConfigError(f"checkpoint {ckpt_file} was trained for material {typed.name}, not {self.material}")
        contour_px = typed.contour_px if self.contour_px is None else self.contour_px
        renderer = effective_renderer(saved.get("renderer"), self._renderer_for(typed))
        polarity = self.polarity or typed.polarity
        check_polarity(polarity, "polarity" if self.polarity else "the checkpoint's material.polarity")
        backgrounds = background_source(self.backgrounds, run_dir)
        if self.n_background and backgrounds is None:
            raise ConfigError(
                f"n_background={self.n_background}: the checkpoint has no run folder with patches/; "
                "give backgrounds=PATCHSET_FOLDER or n_background=0"
            )
        if typed.background_texture.enabled and backgrounds is None:
            raise ConfigError(
                f"checkpoint {ckpt_file} was trained with material.background_texture, which takes its texture from "
                "real background patches, and it has no run folder with patches/; give backgrounds=PATCHSET_FOLDER"
            )
        grey_spread = self.grey_spread
        if grey_spread == "auto":  # on wherever real train patches are at hand (every drgan.train run has them)
            grey_spread = backgrounds is not None
            if not grey_spread:
                log.info("grey_spread=auto: off, the checkpoint has no run folder with real patches (backgrounds=...)")
        if grey_spread and backgrounds is None:
            raise ConfigError(
                "grey_spread=true draws each image's grey levels from the real train patches, and the checkpoint has "
                "no run folder with patches/; give backgrounds=PATCHSET_FOLDER or grey_spread=false"
            )
        given_layout = _resolve_layout(self, saved["material"])
        layout = {group: given_layout.get(group) or saved[group] for group in ("size", "placement")}
        resolved = replace(
            self,
            ckpt=str(ckpt_file),
            grey_spread=grey_spread,
            material=typed.name,
            contour_px=int(contour_px),
            polarity=polarity,
            renderer=renderer,
            backgrounds=str(backgrounds) if backgrounds else None,
            **given_layout,
        )
        return Resolved(resolved, {**saved, **layout, "renderer": renderer}, typed)

    def _renderer_for(self, material: Material) -> dict:
        """The renderer keys given, with ``sampled_spp`` as the spp where ``material``'s imaging renders with Monte
        Carlo grain (secondary electrons: at low spp the particles speckle, which the real images do not); transmission
        renders are noiseless and keep ``renderer.spp``."""
        if self.sampled_spp is None or material.imaging.noiseless:
            return dict(self.renderer)
        return {**self.renderer, "spp": self.sampled_spp}

    @property
    def partial(self) -> PartialSettings:
        """How partial backgrounds are made (drgan.synthetic.backgrounds)."""
        return PartialSettings(self.partial_background, self.partial_max_ignored, self.partial_margin_px)

    def record(self) -> dict:
        """The settings as manifest.json's "config" records them: every field with ``record`` (not out, merge,
        progress), in field order."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.metadata.get("record", True)}

    def fixed(self) -> dict:
        """What config.json records and every later run into the folder must repeat: the ALWAYS settings, then the
        CHANGED ones that are not at their ``before`` value (module docstring)."""
        recorded = [f for f in fields(self) if f.metadata.get("record", True)]
        fixed = {f.name: getattr(self, f.name) for f in recorded if f.metadata.get("fixed", CHANGED) == ALWAYS}
        changed = [f for f in recorded if f.metadata.get("fixed", CHANGED) == CHANGED]
        changed.sort(key=lambda f: _CHANGED_ORDER.index(f.name) if f.name in _CHANGED_ORDER else len(_CHANGED_ORDER))
        for f in changed:
            value = getattr(self, f.name)
            if value != f.metadata.get("before", _field_default(f)):
                fixed[f.name] = value
        return fixed


def _resolve_layout(settings: GenerateSettings, material: dict) -> dict:
    """The size distribution and placement given on the command line, their ``${material.*}`` read from the
    checkpoint's ``material``, each built once: a bad key or value fails here, naming it, before any model is built.
    Returns {group: plain dict} of the groups given."""
    from drgan.core.resolvers import register_resolvers
    from drgan.scene import layout as scene_layout

    register_resolvers()  # ${mul:...} and the others the groups use (already there under every entry point)

    build = {"size": scene_layout.size_from_config, "placement": scene_layout.placement_from_config}
    resolved = {}
    for group, given in (("size", settings.size), ("placement", settings.placement)):
        if not given:
            continue
        try:
            value = OmegaConf.to_container(OmegaConf.create({"material": material, group: given}), resolve=True)[group]
        except Exception as error:  # an interpolation the checkpoint's material cannot fill
            raise ConfigError(f"{group}: {error}") from error
        build[group](dict(value))
        resolved[group] = value
    return resolved


class Resolved(NamedTuple):
    """`GenerateSettings.resolve`'s result."""

    settings: GenerateSettings  # every "null = the checkpoint's" filled in
    model_cfg: dict  # the checkpoint's config with the effective renderer (not recorded: the checkpoint holds it)
    material: Material  # the checkpoint's material, typed once here (the module and the manifest read it)


def defaults(settings_type: type[GenerateSettings] = GenerateSettings) -> dict:
    """Every field's default, by name (what the composed generate.yaml holds when nothing is given)."""
    return {f.name: _field_default(f) for f in fields(settings_type)}


def _field_default(f: dataclasses.Field):
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def _count(key: str, value, minimum: int, note: str = "") -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{key}={value!r}: expected an integer >= {minimum}{note}")


def _integer(key: str, value) -> int:
    """``int(value)`` as the settings always read it (2.0 -> 2), a ConfigError naming ``key`` when it is none."""
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{key}={value!r}: expected an integer") from None


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


FIXED_SETTINGS = tuple(f.name for f in fields(GenerateSettings) if f.metadata["fixed"] == ALWAYS)
