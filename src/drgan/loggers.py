"""MLflow logging for runs that resume, sweeps whose jobs are told apart, and a UI that opens on them.

A run killed mid-epoch resumes from the last epoch end and trains the lost steps again; Lightning would log
those steps a second time. ``MLFlowLogger`` (a Lightning ``MLFlowLogger``) continuing an existing MLflow run
reads, once, the last step logged for each metric and drops any later value logged at or before it, so every
metric's steps stay strictly increasing. (The re-trained steps repeat the lost ones: same seeds, same data.)
A resumed run's config differs from its start at least in ``ckpt_path`` (``last``), often in
``trainer/max_epochs``; MLflow params never change, so each param keeps its first value and the value of the
latest resume goes to the tag ``resumed/<param>``.

In a Hydra sweep (`-m`) every job shares the config's ``run_name`` (it names the sweep's folder); each job's
MLflow run is named after the overrides that set it apart (`sweep_run_name`), e.g. "seed=1".

`python -m drgan.loggers` (`make mlflow-ui`) serves the store that `python -m drgan.train` logs to and prints the
address of each experiment's runs table (MLflow 3's UI otherwise opens on its GenAI pages).
"""

from __future__ import annotations

import argparse
import fcntl
import logging
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from lightning.fabric.utilities.logger import _convert_params, _flatten_dict
from lightning.pytorch.loggers import MLFlowLogger as _LightningMLFlowLogger
from lightning.pytorch.utilities import rank_zero_only

from drgan.errors import ConfigError
from drgan.io import write_bytes
from drgan.resolvers import user_tracking_uri  # noqa: F401  (the user's store is read before any logger changes it)

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


# MLflow 3's UI opens an experiment on its GenAI pages (traces, prompts); this query lands on the runs table of the
# "Model training" view, where runs are listed, compared and plotted.
RUNS_VIEW = "runs?workflowType=machine_learning"


def tracking_store(overrides: Sequence[str] = ()) -> tuple[str, str]:
    """(tracking URI, experiment name) that `python -m drgan.train <overrides>` logs to: its logger config, which
    reads MLFLOW_TRACKING_URI and DRGAN_ROOT as a training run does."""
    from omegaconf import open_dict

    from drgan.configs import compose

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


def runs_url(base_url: str, experiment_id: str) -> str:
    """Address of one experiment's runs table in the MLflow UI at ``base_url``."""
    return f"{base_url.rstrip('/')}/#/experiments/{experiment_id}/{RUNS_VIEW}"


def sqlite_path(tracking_uri: str) -> Path | None:
    return Path(tracking_uri[len("sqlite:///") :]) if tracking_uri.startswith("sqlite:///") else None


def experiments_with_runs(tracking_uri: str) -> list[tuple[str, str, int]]:
    """(name, id, number of runs, at most 1000) of the store's experiments that hold runs, most runs first."""
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=tracking_uri)
    found = [
        (e.name, e.experiment_id, len(client.search_runs([e.experiment_id], max_results=1000)))
        for e in client.search_experiments()
    ]
    return sorted((f for f in found if f[2]), key=lambda f: -f[2])


def describe_runs(tracking_uri: str, experiment: str, base_url: str) -> str:
    """Lines naming the store and, for each experiment with runs, the address of its runs table (``experiment``,
    the one the train config logs to, first)."""
    path = sqlite_path(tracking_uri)
    if path is not None and not path.is_file():  # opening it would create it
        return (
            f"MLflow store {tracking_uri}: no runs yet (python -m drgan.train creates it); "
            f"experiments: {base_url}/#/experiments?workflowType=machine_learning"
        )
    found = experiments_with_runs(tracking_uri)
    found.sort(key=lambda f: f[0] != experiment)
    lines = [f"MLflow store {tracking_uri}: runs tables (open one in a browser):"]
    lines += [f"  {name:<28} {n if n < 1000 else '1000+':>5} runs  {runs_url(base_url, eid)}" for name, eid, n in found]
    if not any(name == experiment for name, _, _ in found):
        lines.append(f"  {experiment}: no runs yet (it appears once python -m drgan.train has started one)")
    return "\n".join(lines)


def _server_up(base_url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{base_url}/health", timeout=2) as response:
            return response.status == 200
    except (urllib.error.URLError, OSError):
        return False


def serve_ui(
    tracking_uri: str, experiment: str, host: str, port: int, workers: int, start_timeout_s: float = 300
) -> int:
    """Serve ``tracking_uri`` with `mlflow ui` until interrupted, printing the runs tables' addresses once it
    answers; a tracking server (http...) is served already: only its addresses are printed. Returns the exit code."""
    if tracking_uri.startswith(("http://", "https://")):
        print(describe_runs(tracking_uri, experiment, tracking_uri), flush=True)
        return 0
    base_url = f"http://{'localhost' if host in ('127.0.0.1', '0.0.0.0') else host}:{port}"
    if _server_up(base_url):
        print(
            f"something already answers at {base_url}: stop it, or choose another port "
            "(make mlflow-ui MLFLOW_PORT=5001)"
        )
        return 1
    print(f"serving MLflow store {tracking_uri} (where python -m drgan.train logs) at {base_url} ...", flush=True)
    command = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", tracking_uri, "--host", host,
               "--port", str(port), "--workers", str(workers)]  # fmt: skip
    # MLflow 3's server also starts job workers (LLM judges' online scoring, trace archival: ~8 processes busy at
    # start-up on a 2-core machine); drgan's runs use none of them.
    env = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", **os.environ}
    server = subprocess.Popen(command, env=env)
    try:
        runs = describe_runs(tracking_uri, experiment, base_url)  # read while the server starts
        deadline = time.monotonic() + start_timeout_s
        while server.poll() is None and not _server_up(base_url) and time.monotonic() < deadline:
            time.sleep(1)
        if server.poll() is None:
            print(runs + "\n(Ctrl-C stops the server)", flush=True)
        return server.wait()
    except KeyboardInterrupt:  # Ctrl-C reached the server too: let it shut down, then make sure it has
        try:
            return server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.terminate()
            return server.wait()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m drgan.loggers",
        description="Serve the MLflow store that python -m drgan.train logs to; print each experiment's runs table.",
    )
    parser.add_argument(
        "overrides", nargs="*", help="train config overrides that pick the store, e.g. material=tio2_tsem"
    )
    parser.add_argument("--host", default="127.0.0.1", help="interface to serve on (default: this machine only)")
    parser.add_argument("--port", type=int, default=5000)
    parser.add_argument("--workers", type=int, default=1, help="server processes (one is plenty for one user)")
    parser.add_argument("--print-only", action="store_true", help="print the store and the runs tables; serve nothing")
    args = parser.parse_args(argv)
    tracking_uri, experiment = tracking_store(args.overrides)
    if args.print_only:
        print(describe_runs(tracking_uri, experiment, f"http://localhost:{args.port}"))
        return 0
    return serve_ui(tracking_uri, experiment, args.host, args.port, args.workers)


if __name__ == "__main__":
    sys.exit(main())
