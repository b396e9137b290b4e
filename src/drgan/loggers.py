"""MLflow logging for runs that resume.

A run killed mid-epoch resumes from the last epoch end and trains the lost steps again; Lightning would log
those steps a second time. ``MLFlowLogger`` (a Lightning ``MLFlowLogger``) continuing an existing MLflow run
reads, once, the last step logged for each metric and drops any later value logged at or before it, so every
metric's steps stay strictly increasing. (The re-trained steps repeat the lost ones: same seeds, same data.)
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

from lightning.pytorch.loggers import MLFlowLogger as _LightningMLFlowLogger
from lightning.pytorch.utilities import rank_zero_only

log = logging.getLogger(__name__)


class MLFlowLogger(_LightningMLFlowLogger):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._resumed = kwargs.get("run_id") is not None
        self._last_step: dict[str, int] | None = None

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
