"""MLflow logging for runs that resume.

A run killed mid-epoch resumes from the last epoch end and trains the lost steps again; Lightning would log
those steps a second time. ``MLFlowLogger`` (a Lightning ``MLFlowLogger``) continuing an existing MLflow run
reads, once, the last step logged for each metric and drops any later value logged at or before it, so every
metric's steps stay strictly increasing. (The re-trained steps repeat the lost ones: same seeds, same data.)
"""

from __future__ import annotations

import fcntl
import logging
from collections.abc import Mapping
from contextlib import contextmanager
from pathlib import Path

from lightning.pytorch.loggers import MLFlowLogger as _LightningMLFlowLogger
from lightning.pytorch.utilities import rank_zero_only

from drgan.io import write_bytes

log = logging.getLogger(__name__)


class MLFlowLogger(_LightningMLFlowLogger):
    """Lightning's MLflow logger that continues a resumed run without repeating steps, and that can keep its run
    id in a run folder (`attach_run_folder`, `start`): one command then serves a first start and every restart."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
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
                log.warning("MLflow run %s of this folder was left RUNNING (killed before its first checkpoint); marked "
                            "KILLED", self.previous_run)
            run = self.run_id  # creates the experiment and run (None on DDP ranks > 0)
        if run and self.id_file is not None:
            write_bytes(self.id_file, run.encode())
        return run

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
            log.debug("MLflow: step %d of %s already logged before the resume; not logged again", step_, sorted(set(metrics) - set(fresh)))
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
