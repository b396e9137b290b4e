"""What the command-line stages share: one way to start a stage as a Hydra app (`stage_main`, `start`: a user's
mistake prints its message, a traceback is for drgan's own bugs), and for the training stages loggers bound to a run
folder, the checkpoint a run resumes from, the composed config as flat MLflow parameters, callbacks built from a config
group (the runtime layer: above models, data and callbacks, below the command-line entry points)."""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from drgan.core.errors import ConfigError, DrganError

log = logging.getLogger(__name__)

MLFLOW_RUN_ID_FILE = "mlflow_run_id.txt"


def stage_help(command: str, docstring: str, settings: Path | None, where: str = "") -> str:
    """A stage's ``--help``: its usage line first, what it does (its module's docstring), then its settings file with
    their comments (``where``: how the text names the file). The same text for ``drgan STAGE --help`` and
    ``python -m drgan.STAGE --help``."""
    text = f"usage: {command} [KEY=VALUE ...]      (drgan --help: every stage)\n\n{docstring.strip()}"
    if settings is not None:
        text += f"\n\nSettings (KEY=VALUE on the command line; {where or settings.name}):\n\n{settings.read_text()}"
    return text


def stage_main(config_path: str, config_name: str):
    """Decorator: ``task(cfg)`` becomes the Hydra app of a stage (``config_path`` relative to the task's module,
    as hydra.main takes it). A user's mistake (a DrganError: a bad setting, path or image) prints its message alone
    on stderr (and into the stage's log file), and the process exits with 1: no "Error executing job" and no
    traceback, which are for drgan's own bugs. ``--help`` (see `start`) prints the stage's own help, `stage_help`."""
    import hydra

    def decorate(task):
        @functools.wraps(task)
        def job(cfg):
            try:
                return task(cfg)
            except DrganError as error:
                report_user_error(error, f"drgan.{config_name}")
                raise SystemExit(1) from None

        app = hydra.main(version_base="1.3", config_path=config_path, config_name=config_name)(job)
        module = sys.modules.get(task.__module__)
        folder = Path(getattr(module, "__file__", "") or ".").parent
        app.settings_file = (folder / config_path / f"{config_name}.yaml").resolve()
        return app

    return decorate


def report_user_error(error: Exception, logger: str) -> None:
    """``error``'s message on stderr, and as an ERROR record in the log files of the root logger (the stage's log)."""
    import sys

    print(f"error: {error}", file=sys.stderr)
    record = logging.LogRecord(logger, logging.ERROR, __file__, 0, "%s", (error,), None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def start(main) -> None:
    """Run a stage's Hydra app from its ``__main__``: Hydra's own errors short (HYDRA_FULL_ERROR=0 unless set),
    drgan's config resolvers and schemas registered first. ``-h``/``--help`` prints the stage's own help
    (`stage_help`) instead of Hydra's generic one."""
    from drgan.launch.configs import setup

    if any(a in ("-h", "--help") for a in sys.argv[1:]) and getattr(main, "settings_file", None) is not None:
        spec = getattr(sys.modules.get("__main__"), "__spec__", None)
        command = f"python -m {spec.name}" if spec is not None else Path(sys.argv[0]).name
        docstring = getattr(sys.modules.get("__main__"), "__doc__", None) or ""
        package = Path(__file__).resolve().parents[1]  # src/drgan
        where = main.settings_file.relative_to(package.parent.parent) if main.settings_file.is_relative_to(
            package.parent.parent) else main.settings_file  # fmt: skip
        with contextlib.suppress(BrokenPipeError):  # `... --help | head`: the reader left
            print(stage_help(command, docstring, main.settings_file, str(where)), flush=True)
        return
    os.environ.setdefault("HYDRA_FULL_ERROR", "0")
    setup()
    main()


def _targets(group) -> list:
    """Every `_target_` entry of a config group, in order (entries without one are ignored)."""
    from hydra.utils import instantiate

    if not group:
        return []
    return [instantiate(entry) for entry in group.values() if isinstance(entry, DictConfig) and "_target_" in entry]


def instantiate_callbacks(cfg: DictConfig | None) -> list:
    """The `callbacks` group's objects, in order, except that ResumeCheckpoint goes first: its epoch-end write
    must come before the other epoch-end work (FID, plots), which a kill may interrupt."""
    from drgan.callbacks.resume import ResumeCheckpoint

    callbacks = _targets(cfg)
    return sorted(callbacks, key=lambda c: not isinstance(c, ResumeCheckpoint))  # stable: the rest keep their order


MLFLOW_PARENT_TAG = "mlflow.parentRunId"  # MLflow's own tag: the UI nests a run under this one


def instantiate_loggers(
    cfg: DictConfig | None, output_dir: Path, resume: bool, tags: dict, parent_run: str | None = None
) -> list:
    """Loggers of the `logger` group, built without contacting a tracking store (see ``start_loggers``). An MLflow
    logger keeps its run id in the run folder: a resumed run continues its own MLflow run. ``parent_run``: the MLflow
    run (e.g. a drgan.pipeline run) this run is a stage of; the UI shows it nested there."""
    if parent_run:
        tags = {**tags, MLFLOW_PARENT_TAG: str(parent_run)}
    from hydra.utils import instantiate

    from drgan.launch.loggers import MLFlowLogger, store_lock

    loggers = []
    for entry in (cfg or {}).values():
        if not isinstance(entry, DictConfig) or "_target_" not in entry:
            continue
        if entry._target_.endswith("MLFlowLogger"):
            id_file = output_dir / MLFLOW_RUN_ID_FILE
            previous = id_file.read_text().strip() if id_file.is_file() else None
            with store_lock(
                str(entry.tracking_uri)
            ):  # its client creates a SQLite store's schema: parallel sweep jobs race
                logger = instantiate(
                    entry, run_id=previous if resume else None, tags={**tags, **(entry.get("tags") or {})}
                )
            if isinstance(logger, MLFlowLogger):
                logger.attach_run_folder(id_file, None if resume else previous)
        else:
            logger = instantiate(entry)
        loggers.append(logger)
    return loggers


def start_loggers(loggers: list) -> None:
    """Open the run of each logger that starts explicitly (drgan.launch.loggers.MLFlowLogger.start)."""
    for logger in loggers:
        getattr(logger, "start", lambda: None)()


def resolve_checkpoint(ckpt_path: str | None, output_dir: Path) -> str | None:
    from drgan.core.checkpoint_io import load_checkpoint

    if ckpt_path in (None, "", "null"):
        return None
    if ckpt_path == "last":
        last = output_dir / "checkpoints" / "last.ckpt"
        if last.is_file():
            load_checkpoint(last, "ckpt_path")  # refused now (code in it, damaged), not after mining
            return str(last)
        log.warning("ckpt_path=last: no %s yet; starting a fresh run", last)
        return None
    path = Path(ckpt_path)
    if not path.is_file():
        raise ConfigError(
            f"ckpt_path={ckpt_path}: no such checkpoint file (or use ckpt_path=last to resume this run folder)"
        )
    load_checkpoint(path, "ckpt_path")
    return str(path)


def flat_config(cfg: DictConfig) -> dict:
    """The composed config as flat "group/key" -> value pairs (MLflow params)."""
    out: dict = {}

    def walk(node, prefix):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}/")
        else:
            out[prefix[:-1]] = node if isinstance(node, (int, float, str, bool)) or node is None else json.dumps(node)

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out
