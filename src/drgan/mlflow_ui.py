"""`drgan mlflow-ui` (`python -m drgan.mlflow_ui`, `make mlflow-ui`): serve the MLflow store that `python -m
drgan.train` logs to and print the address of each experiment's runs table (MLflow 3's UI otherwise opens on its
GenAI pages)."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from pathlib import Path

from drgan.launch.loggers import tracking_store

# MLflow 3's UI opens an experiment on its GenAI pages (traces, prompts); this query lands on the runs table of the
# "Model training" view, where runs are listed, compared and plotted.
RUNS_VIEW = "runs?workflowType=machine_learning"


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
        prog="drgan mlflow-ui",
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
