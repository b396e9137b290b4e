"""MLflow as a user meets it: sweep jobs told apart by their run names, a resumed run's changed params, and the UI
helper's store and addresses."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from drgan.launch.loggers import MLFlowLogger, SweepJob, sweep_run_name, tracking_store
from drgan.mlflow_ui import describe_runs, runs_url


def hydra_jobs(command_line: list[str]) -> list[SweepJob]:
    """The jobs Hydra's basic sweeper makes of a `-m` command line, with the sweep's overrides as typed."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(command_line)
    jobs = [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]
    sweep_dir = "/x/multirun/tio2_sem/sweep"
    return [SweepJob(num, tuple(job), tuple(command_line), sweep_dir) for num, job in enumerate(jobs)]


def test_the_jobs_of_a_sweep_get_distinct_run_names_from_their_own_overrides():
    jobs = hydra_jobs(["debug=fast", "logger=mlflow", "seed=0,1", "model.lr_g=1e-4,2e-4"])
    names = [sweep_run_name("2026-11-23_23-44-47", job) for job in jobs]  # run_name: the default timestamp
    assert names == ["seed=0,model.lr_g=0.0001", "seed=0,model.lr_g=0.0002", "seed=1,model.lr_g=0.0001",
                     "seed=1,model.lr_g=0.0002"]  # fmt: skip
    # A run name given on the command line stays in front; unknown sweep overrides: all of the job's, still distinct.
    named = [sweep_run_name("lr", job) for job in hydra_jobs(["run_name=lr", "debug=fast", "seed=0,1"])]
    assert named == ["lr/seed=0", "lr/seed=1"]
    unknown = [sweep_run_name("t", SweepJob(j.num, j.overrides, None, j.sweep_dir)) for j in jobs]
    assert len(set(unknown)) == 4 and unknown[0] == "debug=fast,logger=mlflow,seed=0,model.lr_g=0.0001"
    assert sweep_run_name("t", SweepJob(3, ("seed=0",), ("seed=0",), "/x")) == "job3"  # -m without a sweep


@pytest.fixture
def hydra_job(tmp_path):
    """Hydra's state in job 1 of `-m debug=fast seed=0,1`, as Hydra sets it in a job process; reset after."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.hydra_config import HydraConfig

    from drgan.launch.configs import setup

    setup()  # the schemas and shared groups the raw Hydra compose below needs

    sweep_dir = tmp_path / "multirun" / "tio2_sem" / "2026-11-23_23-44-47"
    sweep_dir.mkdir(parents=True)
    OmegaConf.save({"hydra": {"overrides": {"task": ["debug=fast", "seed=0,1"]}}}, sweep_dir / "multirun.yaml")
    overrides = ["debug=fast", "seed=1", "hydra.mode=MULTIRUN", "hydra.job.num=1", f"hydra.sweep.dir={sweep_dir}"]
    with initialize_config_dir(
        version_base="1.3", config_dir=str(Path(__file__).resolve().parents[1] / "src" / "drgan" / "conf" / "gan")
    ):
        HydraConfig.instance().set_config(hydra_compose("train", overrides=overrides, return_hydra_config=True))
    yield sweep_dir
    HydraConfig.instance().cfg = None


def test_the_logger_of_a_sweep_job_names_its_run_after_the_job(hydra_job, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    logger = MLFlowLogger(experiment_name="tio2_sem", run_name="2026-11-23_23-44-47", tracking_uri=uri, tags={"a": "1"})
    assert logger._run_name == "seed=1"
    assert logger.tags == {"a": "1", "sweep": "2026-11-23_23-44-47", "sweep_job": "1"}
    resumed = MLFlowLogger(experiment_name="tio2_sem", run_name="keep", tracking_uri=uri, run_id="abc")
    assert resumed._run_name == "keep"  # a resumed run is not renamed


def test_a_single_run_keeps_its_run_name(tmp_path):
    logger = MLFlowLogger(experiment_name="tio2_sem", run_name="sem_a", tracking_uri=f"sqlite:///{tmp_path}/m.db")
    assert logger._run_name == "sem_a" and logger.tags is None


def test_a_resumed_run_keeps_its_params_and_records_what_the_resume_changed_as_tags(tmp_path, caplog):
    """MLflow params never change: `ckpt_path=last` and a larger max_epochs go to tags, with no warning."""
    import mlflow

    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    first = MLFlowLogger(experiment_name="tio2_sem", tracking_uri=uri)
    first.log_hyperparams({"ckpt_path": None, "trainer": {"max_epochs": 1}, "model/lr_g": 2e-4})
    resumed = MLFlowLogger(experiment_name="tio2_sem", tracking_uri=uri, run_id=first.run_id)
    caplog.clear()  # the first start's "Experiment ... not found. Creating it."
    with caplog.at_level(logging.INFO, logger="drgan.launch.loggers"):
        resumed.log_hyperparams(
            {"ckpt_path": "last", "trainer": {"max_epochs": 2}, "model/lr_g": 2e-4, "data/n_train_patches": 130}
        )
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert "ckpt_path=last" in caplog.text
    run = mlflow.MlflowClient(tracking_uri=uri).get_run(first.run_id)
    assert run.data.params == {
        "ckpt_path": "None", "trainer/max_epochs": "1", "model/lr_g": "0.0002", "data/n_train_patches": "130"
    }  # fmt: skip
    resumed_tags = {k: v for k, v in run.data.tags.items() if k.startswith("resumed/")}
    assert resumed_tags == {"resumed/ckpt_path": "last", "resumed/trainer/max_epochs": "2"}
    # the next resume at the first max_epochs: that tag goes, ckpt_path's stays
    again = MLFlowLogger(experiment_name="tio2_sem", tracking_uri=uri, run_id=first.run_id)
    again.log_hyperparams({"ckpt_path": "last", "trainer": {"max_epochs": 1}})
    tags = mlflow.MlflowClient(tracking_uri=uri).get_run(first.run_id).data.tags
    assert {k for k in tags if k.startswith("resumed/")} == {"resumed/ckpt_path"}


def test_the_ui_serves_the_store_train_logs_to_and_links_each_runs_table(tmp_path):
    import mlflow

    import drgan.core.resolvers

    if (
        drgan.core.resolvers.user_tracking_uri() is None
    ):  # the default store: <project>/mlruns, absolute, as drgan.train has it
        assert tracking_store() == (f"sqlite:///{Path.cwd().resolve()}/mlruns/mlflow.db", "tio2_sem")
    uri = f"sqlite:///{tmp_path}/mlruns/mlflow.db"
    assert tracking_store([f"logger.mlflow.tracking_uri={uri}", "material=tio2_tsem"]) == (uri, "tio2_tsem")
    with pytest.raises(Exception, match="logger=mlflow"):
        tracking_store(["logger=none"])

    text = describe_runs(uri, "tio2_sem", "http://localhost:5000")
    assert "no runs yet" in text and not (tmp_path / "mlruns" / "mlflow.db").exists()  # looking creates no store
    client = mlflow.MlflowClient(tracking_uri=uri)
    other, mine = client.create_experiment("other"), client.create_experiment("tio2_sem")
    for experiment in (other, other, mine):
        client.create_run(experiment)
    lines = describe_runs(uri, "tio2_sem", "http://localhost:5000").splitlines()
    assert lines[0] == f"MLflow store {uri}: runs tables (open one in a browser):"
    assert lines[1].split() == ["tio2_sem", "1", "runs", runs_url("http://localhost:5000", mine)]  # its own first
    other_url = f"http://localhost:5000/#/experiments/{other}/runs?workflowType=machine_learning"
    assert lines[2].split() == ["other", "2", "runs", other_url]
