"""The pipeline's settings: its own keys, and each stage's STAGE.KEY=VALUE routed to that stage (the stages and the
keys the pipeline sets for them: stage_table.py)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

from drgan.core.errors import ConfigError
from drgan.core.typed_settings import read_settings, setting, typed
from drgan.pipeline import stage_table
from drgan.pipeline.slurm import SlurmSettings, parse_slurm

CONFIG = Path(__file__).parent.parent / "conf" / "pipeline" / "pipeline.yaml"
OWN_KEYS = (
    "data.dir",
    "name",
    "annotated",
    "corrected",
    "out",
    "redo",
    "mlflow",
    "progress",
    "launcher",
    "only",
    "shard",
    "experiment",
    "parent_run",
)
LAUNCHERS = ("local", "slurm")
STATE_FILE = "pipeline.json"
REPORT_FILE = "report.md"
LOCK_FILE = ".pipeline.lock"


# --- settings ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    data_dir: Path
    name: str
    annotated: Path | None
    out: Path
    redo: str | None
    mlflow: bool
    stages: dict[str, dict[str, str]]  # stage -> {override key (with +/++/~ prefix): value}, in order
    progress: float = 60.0  # seconds between the pipeline's progress lines while a stage runs; 0: none
    launcher: str = "local"  # local: each stage a process here; slurm: each stage a SLURM job (slurm.py)
    slurm: SlurmSettings | None = None  # launcher=slurm's requests (parsed whatever the launcher: a typo fails)
    only: str | None = None  # run this one stage (the stages before it must be done); what a SLURM job runs
    shard: str | None = None  # with only=generate: render this shard i/N of the pairs and nothing else (a job array)
    experiment: str | None = None  # the MLflow experiment; None: pipeline_<name> (a batch: study_<study>)
    parent_run: str | None = None  # an MLflow run above this run's own parent run (a batch's study run)
    argv: tuple[str, ...] = ()  # the command line's words, as given (a SLURM job repeats them)
    corrected: Path | None = (
        None  # a folder of corrected outlines: the finetune stage runs (drgan.segmenters.corrections)
    )

    @property
    def experiment_name(self) -> str:
        return self.experiment or f"pipeline_{self.name}"


def _value_text(value) -> str:
    """A YAML default as the text of a Hydra override value."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_value_text(v) for v in value) + "]"
    return str(value)


def _split_override(text: str) -> tuple[str, str | None]:
    """``key=value`` -> (key, value); ``~key`` (a deletion) -> (``~key``, None)."""
    if text.startswith("~") and "=" not in text:
        return text, None
    if "=" not in text:
        raise ConfigError(f"pipeline: {text!r}: expected KEY=VALUE (e.g. data.dir=/path/to/images or train.seed=1)")
    key, value = text.split("=", 1)
    return key, value


def _stage_key(key: str) -> tuple[str, str] | None:
    """(stage, the key as that stage's command takes it) for ``[+|++|~]STAGE.KEY``; None for the pipeline's own."""
    prefix = re.match(r"^(\+\+|\+|~)?", key).group(0)
    rest = key[len(prefix) :]
    stage, dot, inner = rest.partition(".")
    if dot and stage in stage_table.STAGES:
        if not inner:
            raise ConfigError(f"pipeline: {key!r}: expected {stage}.KEY=VALUE")
        return stage, prefix + inner
    return None


@typed
@dataclass(frozen=True)
class _OwnKeys:
    """The pipeline's own keys (pipeline.yaml), typed by `read_settings` from the YAML's values and the command
    line's (read as YAML values: ``null`` or nothing is null, ``true``/``false`` booleans, numbers numbers)."""

    name: str = setting(check=lambda stage, value: _checked_name(value))
    annotated: Path | None = None
    corrected: Path | None = None
    out: Path | None = None
    redo: str | None = setting(None, check=lambda stage, value: _checked_stage("redo", value))
    mlflow: bool = True
    progress: float = setting(60.0, check=lambda stage, value: _checked_progress(value))
    launcher: str = setting("local", check=lambda stage, value: _checked_choice("launcher", value, LAUNCHERS))
    only: str | None = setting(None, check=lambda stage, value: _checked_stage("only", value))
    shard: str | None = None
    experiment: str | None = None
    parent_run: str | None = None


def _yaml_value(text):
    """A command line's value as YAML reads it (a path or a word stays text); nothing is null."""
    if text is None or text == "":
        return None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def parse_settings(argv: Sequence[str], config_path: Path = CONFIG) -> Settings:
    """The pipeline's settings from its YAML and the command line (``KEY=VALUE`` words); checks names, not files."""
    base = yaml.safe_load(config_path.read_text())
    names = stage_table.STAGES
    own, stages, slurm_words = _route(argv, base, names)
    keys = read_settings(_OwnKeys, {k: v for k, v in own.items() if k != "data.dir"}, "pipeline")
    shard = _checked_shard(keys)
    slurm = parse_slurm(base.get("slurm") or {}, slurm_words, names)
    _check_wired_keys(stages)
    return Settings(
        data_dir=Path(str(own["data.dir"])).expanduser().resolve(),
        name=keys.name,
        annotated=keys.annotated.expanduser().resolve() if keys.annotated else None,
        out=(Path("runs/pipeline") / keys.name if keys.out is None else keys.out.expanduser()).resolve(),
        redo=keys.redo,
        mlflow=keys.mlflow,
        stages=stages,
        progress=keys.progress,
        launcher=keys.launcher,
        slurm=slurm,
        only=keys.only,
        shard=shard,
        experiment=keys.experiment,
        parent_run=keys.parent_run,
        argv=tuple(argv),
        corrected=keys.corrected.expanduser().resolve() if keys.corrected else None,
    )


def _route(argv: Sequence[str], base: dict, names) -> tuple[dict, dict[str, dict[str, str]], dict[str, str]]:
    """(the pipeline's own keys, each stage's keys, the slurm keys): the YAML's, then the command line's words
    routed to them (a stage's key set on the command line replaces the YAML's); an unknown key is a ConfigError."""
    own = {"data.dir": base["data"]["dir"], **{k: base[k] for k in OWN_KEYS if k != "data.dir"}}
    stages: dict[str, dict[str, str]] = {
        s: {str(k): _value_text(v) for k, v in (base["stages"].get(s) or {}).items()} for s in names
    }
    slurm_words: dict[str, str] = {}
    for word in argv:
        key, value = _split_override(word)
        routed = _stage_key(key)
        if key.startswith("slurm.") and value is not None:
            slurm_words[key.removeprefix("slurm.")] = value
        elif routed is not None:
            stage, inner = routed
            stages[stage].pop(inner.lstrip("+~"), None)  # one value per key: the command line's replaces the YAML's
            stages[stage][inner] = value
        elif key in OWN_KEYS:
            own[key] = _yaml_value(value)
        else:
            raise ConfigError(
                f"pipeline: {key}: not a setting of the pipeline ({', '.join(OWN_KEYS)}) nor a stage's key "
                f"(STAGE.KEY=VALUE with STAGE one of {', '.join(names)}; e.g. train.seed=1)"
            )
    if not own["data.dir"]:
        raise ConfigError("pipeline: give data.dir=DIR (the folder of your images)")
    return own, stages, slurm_words


def _checked_name(name) -> str:
    """``name``: the run's material takes it (drgan.launch.configs.material_name)."""
    from drgan.launch.configs import material_name

    return material_name("pipeline", name, "the run's material takes the name and is written as")


def _checked_progress(value) -> float:
    """``progress``: seconds between progress lines, finite and >= 0 (0: none)."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and value >= 0):
        raise ConfigError(f"pipeline: progress={value!r}: expected seconds between progress lines (>= 0; 0: none)")
    return float(value)


def _checked_choice(key: str, value, choices) -> str:
    if value not in choices:
        raise ConfigError(f"pipeline: {key}={value!r}: expected one of {', '.join(choices)}")
    return value


def _checked_stage(key: str, value) -> str | None:
    """``redo``/``only``: a stage's name, or null."""
    if value is None:
        return None
    if value not in stage_table.STAGES:
        raise ConfigError(f"pipeline: {key}={value!r}: expected a stage, one of {', '.join(stage_table.STAGES)}")
    return value


def _checked_shard(keys: _OwnKeys) -> str | None:
    """``shard`` with ``only`` and ``launcher``, checked together: only= runs one stage here, shard= one shard of
    generate."""
    shard, only = keys.shard, keys.only
    if shard is not None:
        parts = shard.split("/")
        if only != "generate" or not re.fullmatch(r"\d+/\d+", shard) or int(parts[0]) >= int(parts[1]):
            raise ConfigError(
                f"pipeline: shard={shard!r}: expected only=generate with shard=i/N (0 <= i < N): one shard of the "
                "pairs, as a SLURM job array's task runs it (slurm.shards=N does this for you)"
            )
    if keys.launcher == "slurm" and only is not None:
        raise ConfigError("pipeline: only= runs one stage here (launcher=local); launcher=slurm submits them all")
    return shard


def _check_wired_keys(stages: dict[str, dict[str, str]]) -> None:
    """A ConfigError for a stage key the pipeline sets itself (the folders that wire the stages together)."""
    for stage, keys in stages.items():
        fixed = sorted(set(k.lstrip("+~") for k in keys) & set(stage_table.PIPELINE_KEYS[stage]))
        if fixed:
            raise ConfigError(
                f"pipeline: {stage}.{fixed[0]} is set by the pipeline (it wires the stages' folders together); "
                f"set out= for another folder, or run python -m {stage_table.stage_spec(stage).command_module} by hand"
            )
