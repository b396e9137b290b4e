"""What spp buys in a GAN training of fixed wall-clock budget: FID against time, from the MLflow store.

    python -m drgan.train -m experiment=tio2_sem run_name=spp_sweep 'logger.mlflow.run_name=spp_sweep_spp${renderer.spp}' \\
        renderer.spp=4,16,64,121 callbacks.fid.spp=16 callbacks.fid.cache_dir=runs/tio2_sem/fid_cache \\
        +trainer.max_time=00:00:08:00 trainer.limit_train_batches=40 'tags=[spp_sweep]'
    python benchmarks/spp_sweep.py [--tag spp_sweep] [--out experiments/benchmarks]

Every run renders its FID images at the same spp (callbacks.fid.spp), so the FID compares what training
at each spp has learned, not the Monte Carlo noise of its renders. Prints a markdown table and writes
spp_sweep.png (FID against wall-clock seconds since the run started and against training seconds).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402


def runs_with_tag(client: MlflowClient, experiment: str, tag: str):
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"no MLflow experiment {experiment!r} in this store")
    runs = client.search_runs([exp.experiment_id], filter_string=f"tags.`{tag}` = '1'")
    return sorted(runs, key=lambda r: int(r.data.params.get("renderer/spp", r.data.params.get("renderer.spp", 0))))


def curve(client: MlflowClient, run):
    """[(wall_s, train_s, epoch, fid)] for each FID of the run."""
    fids = sorted(client.get_metric_history(run.info.run_id, "val/fid"), key=lambda m: m.step)
    steps = {m.step: m.value for m in client.get_metric_history(run.info.run_id, "time/step_s_epoch")}
    epochs = sorted(client.get_metric_history(run.info.run_id, "epoch"), key=lambda m: m.step)
    start = run.info.start_time
    out, train_s, previous_step = [], 0.0, 0
    for fid in fids:
        step_s = steps.get(fid.step, 0.0)
        train_s += step_s * (fid.step - previous_step)
        previous_step = fid.step
        epoch = next((int(e.value) for e in epochs if e.step == fid.step), len(out))
        out.append(((fid.timestamp - start) / 1000.0, train_s, epoch, fid.value))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tracking-uri", default="sqlite:///mlruns/mlflow.db")
    parser.add_argument("--experiment", default="tio2_sem")
    parser.add_argument("--tag", default="spp_sweep")
    parser.add_argument("--out", type=Path, default=Path("experiments/benchmarks"))
    args = parser.parse_args()
    client = MlflowClient(tracking_uri=args.tracking_uri)
    runs = runs_with_tag(client, args.experiment, args.tag)
    fig, (ax_wall, ax_train) = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    print("| training spp | steps | s per step | FID evaluations | first FID | best FID (epoch, wall s) | last FID |")
    print("|---|---|---|---|---|---|---|")
    for run in runs:
        spp = run.data.params.get("renderer/spp", "?")
        points = curve(client, run)
        if not points:
            continue
        wall, train, epochs, fid = zip(*points)
        best = min(range(len(fid)), key=fid.__getitem__)
        step_s = run.data.metrics.get("time/step_s_epoch", float("nan"))
        steps = max(m.step for m in client.get_metric_history(run.info.run_id, "time/step_s"))
        print(
            f"| {spp} | {steps} | {step_s:.2f} | {len(fid)} | {fid[0]:.1f} | {fid[best]:.1f} ({epochs[best]}, {wall[best]:.0f}) | {fid[-1]:.1f} |"
        )
        ax_wall.plot(wall, fid, "o-", label=f"spp {spp}")
        ax_train.plot(train, fid, "o-", label=f"spp {spp}")
    ax_wall.set_xlabel("wall-clock s since start (training + FID passes)")
    ax_train.set_xlabel("training s (sum of step times)")
    ax_wall.set_ylabel("FID (renders at a common spp)")
    ax_wall.legend()
    fig.suptitle("TiO2 SEM: FID against time for training spp 4 / 16 / 64 / 121")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "spp_sweep.png", dpi=110)
    print(f"\nwrote {args.out / 'spp_sweep.png'}")


if __name__ == "__main__":
    main()
