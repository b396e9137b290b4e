"""MLflow logging for runs that resume, sweeps whose jobs are told apart, and a UI that opens on them.

A run killed mid-epoch resumes from the last epoch end and trains the lost steps again; Lightning would log
those steps a second time. ``MLFlowLogger`` (a Lightning ``MLFlowLogger``) continuing an existing MLflow run
reads, once, the last step logged for each metric and drops any later value logged at or before it, so every
metric's steps stay strictly increasing. (The re-trained steps repeat the lost ones: same seeds, same data.)
A resumed run's config differs from its start at least in ``ckpt_path`` (``last``), often in
``trainer/max_epochs``; MLflow params never change, so each param keeps its first value and the value of the
latest resume goes to the tag ``resumed/<param>``.

In a Hydra sweep (`-m`) every job shares the config's ``run_name`` (it names the sweep's folder); each job's
MLflow run is named after the overrides that set it apart (`sweep_run_name`), e.g. "seed=1". `tracking_store` names
the store a train config logs to (`drgan.mlflow_ui` serves it).
"""

from __future__ import annotations

import fcntl
import logging
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from lightning.fabric.utilities.logger import _convert_params, _flatten_dict
from lightning.pytorch.loggers import MLFlowLogger as _LightningMLFlowLogger
from lightning.pytorch.utilities import rank_zero_only

from drgan.core.errors import ConfigError
from drgan.core.io import write_bytes
from drgan.core.resolvers import user_tracking_uri  # noqa: F401  (the user's store is read before any logger changes it)

log = logging.getLogger(__name__)

# Overrides that name the MLflow run: a sweep job's run name keeps their value in front of the job's own overrides.
NAME_KEYS = ("run_name", "logger.mlflow.run_name")
# A resumed run's param whose value changed since the run started: its new value, as the tag "resumed/<param>".
RESUMED_TAG = "resumed/"
PARAM_LENGTH = 250  # Lightning's MLFlowLogger logs str(value)[:250]


@dataclass(frozen=True)
class SweepJob:
    """One job of a Hydra multirun (`-m`): its number, its overrides (e.g. "seed=1"), those of the whole sweep as
    typed (e.g. "seed=0,1"; None when they could not be read) and the sweep's folder."""

    num: int
    overrides: tuple[str, ...]
    sweep_overrides: tuple[str, ...] | None
    sweep_dir: str


def current_sweep_job() -> SweepJob | None:
    """This process's Hydra multirun job, or None (a single run, or no Hydra app running)."""
    import yaml
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    if not HydraConfig.initialized():
        return None
    hydra_cfg = HydraConfig.get()
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return None
    sweep_dir = str(hydra_cfg.sweep.dir)
    sweep_overrides = None
    try:  # the launcher writes the sweep's config, overrides as typed, before it starts the jobs
        sweep_overrides = tuple(OmegaConf.load(Path(sweep_dir) / "multirun.yaml").hydra.overrides.task)
    except (OSError, ValueError, AttributeError, yaml.YAMLError) as error:  # then: all the job's overrides
        log.debug("sweep overrides not read from %s/multirun.yaml: %s", sweep_dir, error)
    return SweepJob(int(hydra_cfg.job.num), tuple(hydra_cfg.overrides.task), sweep_overrides, sweep_dir)


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def sweep_run_name(run_name: str | None, job: SweepJob) -> str:
    """The MLflow run name of a sweep job: its own overrides, i.e. those the whole sweep does not share (for
    `-m debug=fast seed=0,1`: "seed=0", "seed=1"; all of the job's overrides when the sweep's are unknown), after
    ``run_name`` when the command line named the run (`run_name=lr`: "lr/seed=0"); "job<num>" when it has none."""
    shared = set(job.sweep_overrides or ())
    own = [o for o in job.overrides if o not in shared and _override_key(o) not in NAME_KEYS]
    name = ",".join(own) or f"job{job.num}"
    named = any(_override_key(o) in NAME_KEYS for o in job.overrides)
    return f"{run_name}/{name}" if named and run_name else name


class MLFlowLogger(_LightningMLFlowLogger):
    """Lightning's MLflow logger that continues a resumed run without repeating steps, and that can keep its run
    id in a run folder (`attach_run_folder`, `start`): one command then serves a first start and every restart."""

    def __init__(self, **kwargs):
        job = current_sweep_job() if kwargs.get("run_id") is None else None  # a resumed run keeps its name
        if job is not None:  # the jobs of a sweep share run_name: name each after its own overrides
            kwargs["run_name"] = sweep_run_name(kwargs.get("run_name"), job)
            sweep_tags = {"sweep": Path(job.sweep_dir).name, "sweep_job": str(job.num)}
            kwargs["tags"] = {**(kwargs.get("tags") or {}), **sweep_tags}
        super().__init__(**kwargs)
        self._resumed = kwargs.get("run_id") is not None
        self._last_step: dict[str, int] | None = None
        self.id_file: Path | None = None  # where this run's MLflow run id is kept (attach_run_folder)
        self.previous_run: str | None = None  # a run of the same folder that a fresh start replaces

    def attach_run_folder(self, id_file: Path, previous_run: str | None) -> None:
        """Keep the run id in ``id_file`` once started; ``previous_run``: the folder's earlier run, which this fresh
        start replaces (marked KILLED by `start` if its process died while it was RUNNING)."""
        self.id_file, self.previous_run = Path(id_file), previous_run

    def start(self) -> str | None:
        """Open the MLflow run now, under the store lock, and write its id to the run folder; returns the id (None on
        DDP ranks > 0). A fresh start in a folder whose earlier run was killed before its first checkpoint marks
        that earlier run KILLED rather than leaving it RUNNING for ever."""
        with store_lock(str(self._tracking_uri)):
            if self.previous_run and mark_killed(self._tracking_uri, self.previous_run):
                log.warning(
                    "MLflow run %s of this folder was left RUNNING (killed before its first checkpoint); marked KILLED",
                    self.previous_run,
                )
            run = self.run_id  # creates the experiment and run (None on DDP ranks > 0)
        if run and self.id_file is not None:
            write_bytes(self.id_file, run.encode())
        return run

    @rank_zero_only
    def log_hyperparams(self, params) -> None:
        """Lightning's, except on a resumed run: params logged before are not logged again, and one whose value
        changed (``ckpt_path=last``, a larger ``trainer/max_epochs``) keeps its first value, the new one going to
        the tag ``resumed/<param>`` (MLflow refuses to change a param)."""
        if not self._resumed:
            super().log_hyperparams(params)
            return
        flat = {k: (v, str(v)[:PARAM_LENGTH]) for k, v in _flatten_dict(_convert_params(params)).items()}
        run = self.experiment.get_run(self.run_id)
        logged = run.data.params
        new = {k: v for k, (v, _) in flat.items() if k not in logged}
        changed = {k: text for k, (_, text) in flat.items() if k in logged and logged[k] != text}
        if new:
            super().log_hyperparams(new)
        for key, text in changed.items():
            self.experiment.set_tag(self.run_id, RESUMED_TAG + key, text)
        for key in (logged.keys() & flat.keys()) - changed.keys():  # back to its first value after an earlier resume
            if RESUMED_TAG + key in run.data.tags:
                self.experiment.delete_tag(self.run_id, RESUMED_TAG + key)
        if changed:
            log.info(
                "MLflow run %s resumed: %s changed since it started; params keep their first values, the new ones "
                "are its tags %s<param>",
                self.run_id,
                ", ".join(f"{k}={v}" for k, v in changed.items()),
                RESUMED_TAG,
            )

    def last_steps(self) -> dict[str, int]:
        """Metric key -> the largest step logged so far in this MLflow run (read once, then kept up to date)."""
        if self._last_step is None:
            self._last_step = {}
            if self._resumed:
                client = self.experiment
                for key in client.get_run(self.run_id).data.metrics:
                    steps = [m.step for m in client.get_metric_history(self.run_id, key)]
                    if steps:
                        self._last_step[key] = max(steps)
        return self._last_step

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        last, step_ = self.last_steps(), int(step or 0)
        fresh = {k: v for k, v in metrics.items() if step_ > last.get(self._prefixed(k), -1)}
        if len(fresh) < len(metrics):
            log.debug(
                "MLflow: step %d of %s already logged before the resume; not logged again",
                step_,
                sorted(set(metrics) - set(fresh)),
            )
        if fresh:
            super().log_metrics(fresh, step)
            for k in fresh:
                last[self._prefixed(k)] = step_

    def _prefixed(self, key: str) -> str:
        return f"{self._prefix}{self.LOGGER_JOIN_CHAR}{key}" if self._prefix else key


@contextmanager
def store_lock(tracking_uri: str):
    """Serialise first contact with a local MLflow store: parallel sweep jobs (joblib) would otherwise race
    to create the SQLite schema or the experiment. Remote stores (http://...) need no lock."""
    local = None
    if tracking_uri.startswith("sqlite:///"):
        local = Path(tracking_uri[len("sqlite:///") :]).parent
    elif tracking_uri.startswith("file:"):
        local = Path(tracking_uri[len("file:") :])
    if local is None:
        yield
        return
    local.mkdir(parents=True, exist_ok=True)
    with open(local / ".drgan.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def mark_killed(tracking_uri: str, run_id: str) -> bool:
    """Mark an MLflow run that is still RUNNING (its process was killed) as KILLED; True if it was."""
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=tracking_uri)
    try:
        run = client.get_run(run_id)
    except Exception:  # deleted, or another store
        return False
    if run.info.status != "RUNNING":
        return False
    client.set_terminated(run_id, status="KILLED")
    return True


def tracking_store(overrides: Sequence[str] = ()) -> tuple[str, str]:
    """(tracking URI, experiment name) that `python -m drgan.train <overrides>` logs to: its logger config, which
    reads MLFLOW_TRACKING_URI and DRGAN_ROOT as a training run does."""
    from omegaconf import open_dict

    from drgan.launch.configs import compose

    cfg = compose(overrides, config_name="train")
    with open_dict(cfg):  # as drgan.train: the project root, absolute, from the folder it runs in
        cfg.paths.root_dir = str(Path(cfg.paths.root_dir).expanduser().resolve())
    entry = (cfg.get("logger") or {}).get("mlflow")
    if entry is None:
        raise ConfigError(
            f"logger: the train config {' '.join(overrides)} logs to no MLflow store (its logger group "
            f"has {sorted(cfg.get('logger') or {}) or 'no logger'}; expected logger=mlflow, the default)"
        )
    return str(entry.tracking_uri), str(entry.experiment_name)
