"""Fault tests: `python -m drgan.train` SIGKILLed at three points, then resumed with ``ckpt_path=last``.

Each killed-and-resumed run must end where an uninterrupted run with the same seed ends: the same epoch and
step counts, the same generator weights, one FID per epoch, and one MLflow run whose every metric has strictly
increasing steps. Tiny sizes (24 px, spp 1, 3 particles, 3 steps per epoch, random-projection "FID"). Each case
runs two to three training processes (~80 s for the mid-epoch kill on a 2-core machine): the whole module is `slow`
(`make test-slow`, CI); the default run resumes in-process (test_train.py, test_callbacks.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_train import make_images, tiny_overrides

pytestmark = pytest.mark.slow
TESTS = Path(__file__).resolve().parent
EPOCHS, BATCHES = 3, 3


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    return make_images(tmp_path_factory.mktemp("real") / "images")


def train(images: Path, out: Path, extra=(), expect_kill: bool = False) -> None:
    uri = f"sqlite:///{out.parent}/mlruns/mlflow.db"
    overrides = tiny_overrides(images, out, logger="mlflow", extra=[
        f"logger.mlflow.tracking_uri={uri}", f"trainer.max_epochs={EPOCHS}", f"trainer.limit_train_batches={BATCHES}",
        "trainer.log_every_n_steps=1", "callbacks.fid.n_images=4", *extra])  # fmt: skip
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "DRGAN_RENDER_THREADS": "1",
        "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    }
    result = subprocess.run(
        [sys.executable, "-m", "drgan.train", *overrides],
        cwd=out.parent,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    if expect_kill:
        assert result.returncode == -9, f"expected a SIGKILL, got {result.returncode}: {result.stderr[-2000:]}"
    else:
        assert result.returncode == 0, result.stderr[-3000:]


def generator_weights(out: Path) -> dict[str, torch.Tensor]:
    state = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["state_dict"]
    return {k: v for k, v in state.items() if k.startswith(("generator.", "discriminator."))}


def mlflow_runs(out: Path):
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{out.parent}/mlruns/mlflow.db")
    experiment = client.get_experiment_by_name("tio2_sem")
    return client, client.search_runs([experiment.experiment_id])


@pytest.fixture(scope="module")
def reference(images, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "run"
    train(images, out)
    return out


KILLS = {
    # (a) mid-epoch: after the 2nd batch of epoch 1
    "mid_epoch": lambda marker: [
        f"+callbacks.kill={{_target_:faultpoints.KillAtBatch,epoch:1,batch:1,marker:{marker}}}"
    ],
    # (b) right after epoch 1's data loop and its last.ckpt write, before FID
    "after_data_loop": lambda marker: [
        "callbacks.resume._target_=faultpoints.ResumeThenKill",
        "+callbacks.resume.epoch=1",
        f"+callbacks.resume.marker={marker}",
    ],
    # (c) during epoch 1's FID pass (feature extraction #3: real patches, epoch 0's renders, epoch 1's renders)
    "during_fid": lambda marker: [
        "callbacks.fid.extractor._target_=faultpoints.KillingFeatures",
        "+callbacks.fid.extractor.call=3",
        f"+callbacks.fid.extractor.marker={marker}",
    ],
}


@pytest.mark.parametrize("kill", sorted(KILLS))
def test_killed_run_resumes_to_the_uninterrupted_result(kill, images, reference, tmp_path):
    out = tmp_path / "run"
    marker = tmp_path / "killed"
    switch = KILLS[kill](marker)
    train(images, out, switch, expect_kill=True)
    assert marker.is_file()
    train(images, out, [*switch, "ckpt_path=last"])

    done, ref = json.loads((out / "metrics.json").read_text()), json.loads((reference / "metrics.json").read_text())
    assert (done["epoch"], done["global_step"]) == (ref["epoch"], ref["global_step"]) == (EPOCHS, 2 * EPOCHS * BATCHES)

    # Same weights as the uninterrupted run. Bitwise: same seeds, same data order and augmentations, same
    # dropout masks (the global RNG state travels in last.ckpt), and the CPU renders and networks are
    # deterministic for a fixed thread count (OMP_NUM_THREADS=1 here; Dr.Jit's LLVM backend replays the same
    # sample pattern for the same seed).
    mine, theirs = generator_weights(out), generator_weights(reference)
    assert mine.keys() == theirs.keys()
    differing = [k for k in mine if not torch.equal(mine[k], theirs[k])]
    worst = max((float((mine[k].double() - theirs[k].double()).abs().max()) for k in differing), default=0.0)
    assert not differing, f"weights differ from the uninterrupted run by up to {worst:.3g}: {differing[:4]}"

    # One FID per epoch, equal to the uninterrupted run's.
    history = json.loads((out / "checkpoints" / "best_epoch.json").read_text())["history"]
    ref_history = json.loads((reference / "checkpoints" / "best_epoch.json").read_text())["history"]
    assert [h["epoch"] for h in history] == list(range(EPOCHS))
    assert [h["fid"] for h in history] == pytest.approx([h["fid"] for h in ref_history], rel=1e-9)

    # One MLflow run, continued; every metric's steps strictly increasing.
    client, runs = mlflow_runs(out)
    assert len(runs) == 1 and runs[0].info.status == "FINISHED"
    run_id = runs[0].info.run_id
    assert (out / "mlflow_run_id.txt").read_text() == run_id
    for key in runs[0].data.metrics:
        steps = [m.step for m in client.get_metric_history(run_id, key)]
        assert steps == sorted(set(steps)), f"{key}: steps {steps} logged twice or out of order"
    fids = client.get_metric_history(run_id, "val/fid")
    assert len(fids) == EPOCHS


def test_kill_before_first_checkpoint_marks_the_mlflow_run_killed(images, tmp_path):
    out = tmp_path / "run"
    marker = tmp_path / "killed"
    kill = [f"+callbacks.kill={{_target_:faultpoints.KillAtBatch,epoch:0,batch:1,marker:{marker}}}"]
    train(images, out, kill, expect_kill=True)
    assert not (out / "checkpoints" / "last.ckpt").exists()
    _, runs = mlflow_runs(out)
    assert [r.info.status for r in runs] == ["RUNNING"]  # what the kill left
    train(images, out, [*kill, "ckpt_path=last", "trainer.max_epochs=1"])  # no checkpoint: a fresh start
    _, runs = mlflow_runs(out)
    assert sorted(r.info.status for r in runs) == ["FINISHED", "KILLED"]


def test_train_longer_trains_only_the_new_epochs(images, reference, tmp_path):
    """ckpt_path=last after a finished run with a larger max_epochs: the old epochs are not trained again."""
    import shutil

    out = tmp_path / "run"
    shutil.copytree(reference, out)
    shutil.copytree(reference.parent / "mlruns", tmp_path / "mlruns")
    train(images, out, ["ckpt_path=last", f"trainer.max_epochs={EPOCHS + 1}"])
    done = json.loads((out / "metrics.json").read_text())
    assert (done["epoch"], done["global_step"]) == (EPOCHS + 1, 2 * (EPOCHS + 1) * BATCHES)
    client, runs = mlflow_runs(out)
    assert len(runs) == 1
    steps = [m.step for m in client.get_metric_history(runs[0].info.run_id, "train/g_loss")]
    assert steps == sorted(set(steps)) and len(steps) == (EPOCHS + 1) * BATCHES
    history = json.loads((out / "checkpoints" / "best_epoch.json").read_text())["history"]
    assert [h["epoch"] for h in history] == list(range(EPOCHS + 1))
