"""A run that knows when it is done: the early-stopping rule, the wall-clock budget, the KID screen of the FID
callback, and the stop reason in metrics.json and MLflow (tiny trainings, random-projection "FID")."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
from test_train import images, run_train, tiny_overrides  # noqa: F401  (images: the module fixture)

from drgan.callbacks import FIDEarlyStopping, RandomProjectionFeatures, should_stop
from drgan.core.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def train_one_batch_epochs(images, out, extra, logger="none"):  # noqa: F811
    """A tiny training whose epochs are one step each (an evaluation after every step), with ``extra`` overrides."""
    return run_train(tiny_overrides(images, out, logger=logger, extra=["trainer.limit_train_batches=1", *extra]))


def entries(fids, steps=None):
    return [{"epoch": i, "fid": f, "step": (steps or range(0, 1000, 10))[i]} for i, f in enumerate(fids)]


def test_patience_counts_evaluations_since_the_lowest_fid():
    assert should_stop(entries([100, 90]), patience=2) is None
    assert should_stop(entries([100, 90, 95]), patience=2) is None
    reason = should_stop(entries([100, 90, 95, 91]), patience=2)
    assert reason is not None and "90" in reason and "epoch 1" in reason
    assert should_stop(entries([100, 90, 95, 91]), patience=3) is None
    assert should_stop(entries([100, 90, 95, 89]), patience=2) is None  # a new lowest resets the count


def test_a_screened_out_evaluation_counts_as_no_improvement_and_min_delta_must_be_beaten():
    assert should_stop(entries([100, math.nan, math.nan]), patience=2) is not None
    assert should_stop(entries([math.nan, math.nan, math.nan]), patience=1) is None  # nothing to improve on yet
    assert should_stop(entries([100, 99.5, 99.2]), patience=2, min_delta=1.0) is not None
    assert should_stop(entries([100, 99.5, 98.9]), patience=2, min_delta=1.0) is None


def test_patience_in_steps():
    history = entries([100, 90, 95, 96], steps=[45, 90, 135, 180])
    assert should_stop(history[:3], patience=None, patience_steps=90) is None  # 45 steps since the lowest
    assert "90 steps" in should_stop(history, patience=None, patience_steps=90)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"patience": 0}, "patience=0"),
        ({"patience": 1.5}, "patience=1.5"),
        ({"patience_steps": -3}, "patience_steps=-3"),
        ({"patience": None, "patience_steps": None, "max_minutes": None}, "all null"),
        ({"min_delta": -1}, "min_delta=-1"),
        ({"max_minutes": 0}, "max_minutes=0"),
    ],
)
def test_early_stopping_refuses_settings_that_cannot_work(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        FIDEarlyStopping(**kwargs)


def rising_fid(monkeypatch):
    """Every full FID of the run larger than the one before: the run can only get worse."""
    from drgan.metrics.feature_distances import FeatureStats

    calls = []

    def fid(self, other):
        calls.append(1)
        return 100.0 + len(calls)

    monkeypatch.setattr(FeatureStats, "fid", fid)
    return calls


def test_a_run_whose_fid_only_rises_stops_after_patience_and_says_why(images, tmp_path, monkeypatch):  # noqa: F811
    import mlflow

    rising_fid(monkeypatch)
    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    out = tmp_path / "run"
    train_one_batch_epochs(
        images,
        out,
        [
            f"logger.mlflow.tracking_uri={uri}",
            "trainer.max_epochs=6",
            "callbacks.early_stopping.patience=2",
            "callbacks.best_epoch.brightness_range=[0.01,100]",  # every epoch's grey in range: patience alone decides
        ],
        logger="mlflow",
    )
    done = json.loads((out / "metrics.json").read_text())
    assert done["stop_reason"] == "patience" and "patience 2" in done["stop_message"]
    best = json.loads((out / "checkpoints" / "best_epoch.json").read_text())
    # evaluations after iterations 1, 2, 3: the lowest is the first, then 2 worse
    assert best["epoch"] == 0 and [h["epoch"] for h in best["history"]] == [0, 1, 2]
    run = mlflow.MlflowClient(tracking_uri=uri).get_run((out / "mlflow_run_id.txt").read_text())
    assert run.data.tags["stop_reason"] == "patience" and "patience 2" in run.data.tags["stop_message"]


def test_patience_waits_while_no_epoch_has_the_real_grey():
    """The rule on a trainer's callbacks (no training): FIDs only rising, patience 1. While no evaluated epoch of the
    best-epoch rule's history is within its grey range, patience stops nothing; once one is, it stops; with
    wait_for_grey=false it stops regardless."""
    from types import SimpleNamespace

    from drgan.callbacks import BestEpochCallback, FIDCallback

    def decide(grey_ok: list[bool], wait: bool = True) -> bool:
        fid = FIDCallback(extractor=RandomProjectionFeatures(dim=4))
        fid.history = [{"epoch": i, "fid": 100.0 + i, "step": 10 * i} for i in range(len(grey_ok))]
        best = BestEpochCallback(brightness_range=[0.9, 1.1])
        best.history = [
            {"epoch": i, "fid": 100.0 + i, "particle_brightness": 1.0 if ok else 0.5, "background_brightness": 1.0,
             "contrast": 2.0}
            for i, ok in enumerate(grey_ok)
        ]  # fmt: skip
        stopper = FIDEarlyStopping(patience=1, wait_for_grey=wait)
        stopper._start = 0.0
        trainer = SimpleNamespace(callbacks=[fid, best, stopper], current_epoch=len(grey_ok) - 1, should_stop=False,
                                  is_global_zero=True)  # fmt: skip
        stopper.on_train_epoch_end(trainer, None)
        return trainer.should_stop

    assert not decide([False, False])  # patience is due, but nothing usable has been seen
    assert decide([True, False])  # an epoch within the grey exists: patience decides
    assert decide([False, False], wait=False)


@pytest.mark.slow  # four epochs of training@pytest.mark.slow  # four epochs of training: ~20 s on 2 cores (the default run's longest)
def test_a_run_without_early_stopping_goes_to_max_epochs(images, tmp_path, monkeypatch):  # noqa: F811
    rising_fid(monkeypatch)
    out = tmp_path / "run"
    train_one_batch_epochs(images, out, ["trainer.max_epochs=4", "~callbacks.early_stopping"])
    done = json.loads((out / "metrics.json").read_text())
    assert done["stop_reason"] == "max_epochs" and done["epoch"] == 4


def test_the_budget_stops_before_an_epoch_that_would_not_fit_and_says_it_cut_the_run_short(
    images,
    tmp_path,
    caplog,  # noqa: F811
):
    out = tmp_path / "run"
    # 0.003 min = 0.18 s: the first epoch (render, FID, plots) takes longer, so no second epoch fits
    with caplog.at_level(logging.WARNING, logger="drgan.callbacks.early_stop"):
        train_one_batch_epochs(images, out, ["trainer.max_epochs=5", "callbacks.early_stopping.max_minutes=0.003"])
    done = json.loads((out / "metrics.json").read_text())
    assert done["stop_reason"] == "budget" and "max_minutes=0.003" in done["stop_message"]
    assert done["epoch"] == 1
    warned = [r.getMessage() for r in caplog.records if "safety net cut this run short" in r.getMessage()]
    assert len(warned) == 1 and "after epoch 0 of trainer.max_epochs=5" in warned[0]


def kid_by_epoch(monkeypatch, values):
    """The screen's KID (and the full one) of epoch e: values[e] (the callback seeds KID with the epoch)."""
    import drgan.callbacks.fid as fid_module

    monkeypatch.setattr(fid_module, "kid", lambda a, b, subsets, size, seed: (float(values[seed]), 0.0))


@pytest.mark.slow  # three epochs of training: ~14 s on 2 cores
def test_the_kid_screen_skips_the_full_fid_of_an_epoch_that_is_no_better(images, tmp_path, monkeypatch):  # noqa: F811
    kid_by_epoch(monkeypatch, [1.0, 1.5, 1.1])  # epoch 1: 50 % above the lowest screen; epoch 2: within 20 %
    out = tmp_path / "run"
    train_one_batch_epochs(
        images,
        out,
        [
            "trainer.max_epochs=3",
            "callbacks.fid.n_images=8",
            "callbacks.fid.screen_images=4",
            "callbacks.fid.screen_margin=0.2",
            "~callbacks.early_stopping",
        ],
    )
    best = json.loads((out / "checkpoints" / "best_epoch.json").read_text())
    assert [h["epoch"] for h in best["history"]] == [0, 2]  # the screened-out epoch never competes
    import torch

    state = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    history = state["callbacks"]["FIDCallback"]["history"]
    assert [h["n_images"] for h in history] == [8, 4, 8] and [h["step"] for h in history] == [1, 2, 3]
    assert math.isnan(history[1]["fid"]) and np.isfinite(history[0]["fid"]) and np.isfinite(history[2]["fid"])
    assert [h["screen_kid"] for h in history] == [1.0, 1.5, 1.1]
    assert not list((out / "checkpoints" / "epochs").glob("epoch_001.ckpt"))


@pytest.mark.slow  # two trainings: ~10 s
def test_the_progress_bar_shows_a_screened_out_epoch_as_screened(images, tmp_path, monkeypatch):  # noqa: F811
    """The bar shows the last logged val/fid: NaN for an epoch the screen turned away, which reads "screened"."""
    from drgan.callbacks import TrainingProgressBar

    kid_by_epoch(monkeypatch, [1.0, 1.5])  # epoch 1: 50 % above the lowest screen, screened out
    shown = []

    def on_train_end(self, trainer, pl_module):
        shown.append(self.get_metrics(trainer, pl_module))

    monkeypatch.setattr(TrainingProgressBar, "on_train_end", on_train_end)
    bar = ["callbacks.progress_bar._target_=drgan.callbacks.TrainingProgressBar"]
    screen = ["callbacks.fid.n_images=8", "callbacks.fid.screen_images=4", "~callbacks.early_stopping"]
    train_one_batch_epochs(images, tmp_path / "run", ["trainer.max_epochs=2", *screen, *bar])
    assert shown[-1]["val/fid"] == "screened"
    train_one_batch_epochs(images, tmp_path / "one", ["trainer.max_epochs=1", *screen, *bar])
    assert np.isfinite(shown[-1]["val/fid"])  # a full FID is shown as its value


@pytest.mark.slow  # two trainings: ~10 s
def test_a_full_fid_after_the_screen_equals_the_fid_without_one(images, tmp_path):  # noqa: F811
    """The screen's images are the first of the full set (same seeds): the candidate's FID is unchanged."""
    fids = []
    for name, screen in (("plain", "null"), ("screened", "4")):
        out = tmp_path / name
        metrics = train_one_batch_epochs(
            images, out, ["trainer.max_epochs=1", "callbacks.fid.n_images=9", f"callbacks.fid.screen_images={screen}"]
        )
        fids.append(metrics["val/fid"])
    assert np.isfinite(fids[0]) and fids[0] == pytest.approx(fids[1], rel=1e-9)


def test_lightnings_max_time_is_named_as_the_reason(images, tmp_path):  # noqa: F811
    out = tmp_path / "run"
    train_one_batch_epochs(
        images, out, ["trainer.max_epochs=5", "+trainer.max_time=00:00:00:01", "~callbacks.early_stopping"]
    )
    done = json.loads((out / "metrics.json").read_text())
    assert done["stop_reason"] == "max_time" and "trainer.max_time" in done["stop_message"] and done["epoch"] < 5
