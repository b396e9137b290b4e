"""What a pipeline run keeps beside its stages: pipeline.json (State), the folder's lock, and its MLflow runs
(Tracker)."""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from drgan.core.errors import ConfigError
from drgan.core.io import write_bytes, write_json
from drgan.pipeline.settings import LOCK_FILE, Settings
from drgan.pipeline.stages import Stage

log = logging.getLogger("drgan.pipeline")

# --- state, lock, MLflow ----------------------------------------------------------------------------------


class State:
    """pipeline.json: per stage its recorded arguments, state (running / done / failed), times."""

    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.is_file() else {"stages": {}}

    def stage(self, name: str) -> dict:
        return self.data["stages"].get(name, {})

    def update(self, name: str, **values) -> None:
        self.data["stages"].setdefault(name, {}).update(values)
        write_json(self.path, self.data)

    def save(self) -> None:
        write_json(self.path, self.data)

    def forget(self, name: str) -> None:
        self.data["stages"].pop(name, None)
        write_json(self.path, self.data)


@contextlib.contextmanager
def folder_lock(out: Path, wait: float = 0.0):
    """The run folder's lock, held while a pipeline (or a submission) works in it; ``wait``: seconds to wait for it
    (a SLURM job whose submission is still writing) before refusing."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / LOCK_FILE, "w") as handle:
        deadline = time.monotonic() + wait
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise ConfigError(
                        f"pipeline: another drgan.pipeline is running on {out} (its lock {out / LOCK_FILE} is held); "
                        "wait for it, or give this one another name="
                    ) from None
                time.sleep(1.0)
        yield


class Tracker:
    """The MLflow parent run of a pipeline (its id kept in out/mlflow_parent_run_id.txt, so a resumed pipeline
    continues it) and the child runs of the stages that log nothing themselves. Any store error only warns."""

    ID_FILE = "mlflow_parent_run_id.txt"

    def __init__(self, s: Settings):
        self.client = self.parent = None
        if not s.mlflow:
            return
        try:
            import mlflow

            from drgan.launch.loggers import tracking_store

            conf = (
                s.out / "drgan_conf"
            )  # the run's own configs, once the profile wrote them (Hydra warns of a missing one)
            uri, _ = tracking_store([f"hydra.searchpath=[file://{conf}]"] if conf.is_dir() else [])
            self.client = mlflow.MlflowClient(tracking_uri=uri)
            experiment_id = experiment_id_of(self.client, uri, s.experiment_name)
            id_file = s.out / self.ID_FILE
            previous = id_file.read_text().strip() if id_file.is_file() else None
            if previous:
                self.client.update_run(previous, status="RUNNING")
                self.parent = previous
            else:
                tags = {"data_dir": str(s.data_dir), "output_dir": str(s.out)}
                if s.parent_run:
                    tags["mlflow.parentRunId"] = s.parent_run
                run = self.client.create_run(experiment_id, run_name=s.name, tags=tags)
                self.parent = run.info.run_id
                write_bytes(id_file, self.parent.encode())
            self.experiment_id = experiment_id
        except Exception as error:  # noqa: BLE001  (a tracking store must never stop the pipeline)
            log.warning("MLflow: no parent run (%s); the stages run without it", str(error).splitlines()[0])
            self.client = self.parent = None

    def child(self, stage: Stage, seconds: float, metrics: Mapping[str, float], artifacts: Sequence[Path]) -> None:
        """A finished child run for a stage that has no MLflow run of its own."""
        if self.client is None:
            return
        try:
            run = self.client.create_run(
                self.experiment_id,
                run_name=stage.name,
                tags={"mlflow.parentRunId": self.parent, "stage": stage.name, "output_dir": str(stage.folder)},
            )
            rid = run.info.run_id
            self.client.log_param(rid, "command", " ".join(stage.recorded())[:6000])
            self.client.log_metric(rid, "time/wall_s", seconds)
            for key, value in metrics.items():
                self.client.log_metric(rid, key, float(value))
            for path in artifacts:
                if path.is_file():
                    self.client.log_artifact(rid, str(path))
            self.client.set_terminated(rid, "FINISHED")
        except Exception as error:  # noqa: BLE001
            log.warning("MLflow: stage %s not logged (%s)", stage.name, str(error).splitlines()[0])

    def finish(self, status: str, metrics: Mapping[str, float] = {}) -> None:
        """Log ``metrics`` and close the parent run with ``status``; RUNNING (a SLURM job's stage, later ones to
        come) leaves it open."""
        if self.client is None:
            return
        try:
            for key, value in metrics.items():
                self.client.log_metric(self.parent, key, float(value))
            if status != "RUNNING":
                self.client.set_terminated(self.parent, status)
        except Exception as error:  # noqa: BLE001
            log.warning("MLflow: parent run not closed (%s)", str(error).splitlines()[0])


def experiment_id_of(client, uri: str, name: str) -> str:
    """The id of MLflow experiment ``name`` in the store at ``uri``, created if new (under the store's lock: jobs on
    many nodes may create it at once)."""
    from drgan.launch.loggers import store_lock

    with store_lock(uri):
        experiment = client.get_experiment_by_name(name)
        return experiment.experiment_id if experiment else client.create_experiment(name)
