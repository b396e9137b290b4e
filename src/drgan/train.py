"""`python -m drgan.train material=sio2_him data.dir=/path/to/images`: train DiffRenderGAN.

Composes conf/gan/train.yaml, mines the real patches, and fits the GANModule with Lightning. Everything of
one run lands in its folder, runs/<material>/<run_name>/ (patches/, checkpoints/, train.log, metrics.json,
.hydra/); metrics and parameters go to MLflow (one experiment per material, one run per training run).

Fine-tune: `init_from=<another run's best.ckpt>` starts a new run from that run's FCN and D weights.

Resume: run again with the same run_name and `ckpt_path=last`, e.g.
    python -m drgan.train run_name=exp1 trainer.max_epochs=80 ckpt_path=last
The same run_name gives the same folder, hence its checkpoints/last.ckpt, its cached patches and its
MLflow run (whose id is kept in the folder). `ckpt_path=last` with no checkpoint yet starts afresh, so
one command serves a first start and every restart (e.g. a preempted cluster job).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, open_dict

from drgan.core.errors import ConfigError
from drgan.core.io import write_json
from drgan.core.typed_settings import read_settings, typed
from drgan.launch.runtime import (
    flat_config,
    instantiate_callbacks,
    instantiate_loggers,
    resolve_checkpoint,
    stage_main,
    start,
    start_loggers,
)

log = logging.getLogger(__name__)


@typed
@dataclass(frozen=True)
class TrainRun:
    """The keys of conf/gan/train.yaml that say how a run starts and is recorded, typed (`read_settings`); the groups
    (material, renderer, model, data, callbacks, logger, trainer) are typed by their schemas and built by Hydra."""

    seed: int = 0
    ckpt_path: str | None = None  # null: fresh; "last": resume from the run folder's last.ckpt; or a path
    init_from: Path | None = None  # another run's checkpoint: its FCN and D weights start this run
    tags: tuple[str, ...] = ()
    parent_run: str | None = None
    optimized_metric: str | None = None

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainRun:
        run = read_settings(cls, cfg, "train")
        if run.init_from is not None and not run.init_from.expanduser().is_file():  # before any data is mined
            raise ConfigError(f"init_from={run.init_from}: no such checkpoint file (a .ckpt written by drgan.train)")
        return run


def train(cfg: DictConfig) -> dict:
    """Fit one run; return its final metrics (last step/epoch values, plus time/wall_s).

    Everything that needs no pixels is built or checked first (seconds): the data settings, folder and split, then
    scene, meshes, renderer and model, the checkpoint to resume, init_from, callbacks, loggers, trainer. Only then
    are the patches mined (20-70 s for the TiO2 SEM images), and only then does training start."""
    import lightning.pytorch as L

    wall_start = time.perf_counter()
    run = TrainRun.from_config(cfg)
    _check_data(cfg)
    with open_dict(cfg):  # absolute project root: every path of the run derives from it
        cfg.paths.root_dir = str(Path(cfg.paths.root_dir).expanduser().resolve())
    output_dir = Path(cfg.paths.output_dir)
    L.seed_everything(run.seed, workers=True)
    datamodule, model, ckpt_path = _build_model(cfg, run, output_dir)
    loggers, trainer = _build_trainer(cfg, run, output_dir, resumed=ckpt_path is not None)

    output_dir.mkdir(parents=True, exist_ok=True)
    datamodule.setup("fit")
    m = cfg.model.n_constellations or datamodule.n_train
    if len(model.phi_bank) != int(m):
        model.set_constellations(int(m))
    start_loggers(loggers)
    params = flat_config(cfg)
    params.update({"data/n_train_patches": datamodule.n_train, "model/m": int(m)})
    for logger in loggers:
        try:
            logger.log_hyperparams(params)
        except Exception as error:  # an unreachable store must not stop training (a resume's changes: tags)
            log.warning("%s: config params not (all) logged: %s", type(logger).__name__, str(error).splitlines()[0])

    log.info(
        "training %s: %d real patches, m=%d constellations, run folder %s",
        cfg.material.name,
        datamodule.n_train,
        m,
        output_dir,
    )
    trainer.fit(
        model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True
    )  # drgan.core.checkpoint_io: no code runs
    return _finish(trainer, model, loggers, output_dir, wall_start)


def _check_data(cfg: DictConfig) -> None:
    """data.dir, set before anything is built."""
    if not cfg.data.dir:
        raise ConfigError(
            f"data.dir is not set: material={cfg.material.name} is made for "
            f"{cfg.material.made_for or 'images drgan does not ship'}, and no such images are configured. Point "
            f"it at your images: python -m drgan.train material={cfg.material.name} data.dir=/path/to/images (check the "
            "material fits them first: python -m drgan.profile data.dir=/path/to/images name=my_particles writes one)"
        )


def _build_model(cfg: DictConfig, run: TrainRun, output_dir: Path):
    """(datamodule with its ids resolved, GANModule, the checkpoint to resume or None), the images' polarity and
    particle size checked against the material and init_from's weights copied into a fresh run: no pixel read."""
    from hydra.utils import instantiate

    from drgan.models.gan_module import GANModule
    from drgan.scene.config import typed_material

    datamodule = instantiate(cfg.data, resolution=int(cfg.renderer.resolution))
    datamodule.resolve_ids()
    material = typed_material(cfg.material)  # typed once: the data's checks and the model read it
    datamodule.check_fits(material)  # polarity and particle size against the material: seconds, before mining
    model = GANModule.from_config(cfg, base_dir=cfg.paths.root_dir, material=material)  # phi bank: after mining
    ckpt_path = resolve_checkpoint(run.ckpt_path, output_dir)
    if run.init_from is not None and ckpt_path is None:  # a resumed run already holds its (fine-tuned) weights
        copied = model.load_weights(run.init_from.expanduser())
        log.info(
            "init_from=%s: %d weight tensors of the FCN and discriminator copied; a fresh run from epoch 0",
            run.init_from,
            copied,
        )
    if model.textured and int(datamodule.n_background or 0) < 1:  # the texture comes from mined background patches
        raise ConfigError(
            "material.background_texture.enabled: no real background patches to take the texture from "
            f"(data.n_background={datamodule.n_background}; set data.n_background > 0)"
        )
    return datamodule, model, ckpt_path


def _build_trainer(cfg: DictConfig, run: TrainRun, output_dir: Path, *, resumed: bool):
    """(loggers, Lightning trainer with the config's callbacks), each callback's inputs checked (e.g. the FID
    network's file and hash) before any patch is mined."""
    from hydra.utils import instantiate

    tags = {"material": str(cfg.material.name), "output_dir": str(output_dir)}
    tags.update({t: "1" for t in run.tags})
    loggers = instantiate_loggers(cfg.logger, output_dir, resume=resumed, tags=tags, parent_run=run.parent_run)
    callbacks = instantiate_callbacks(cfg.callbacks)
    for callback in callbacks:
        getattr(callback, "check_ready", lambda: None)()
    return loggers, instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)


def _finish(trainer, model, loggers, output_dir: Path, wall_start: float) -> dict:
    """The run's final metrics: logged, its stop reason tagged in MLflow, written to metrics.json (rank 0)."""
    from drgan.callbacks.early_stop import stop_reason

    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if getattr(v, "numel", lambda: 1)() == 1}
    metrics["time/wall_s"] = time.perf_counter() - wall_start
    metrics["train/skipped_steps_total"] = float(model.skipped_steps)
    kind, why = stop_reason(trainer)
    for logger in loggers:
        logger.log_metrics({"time/wall_s": metrics["time/wall_s"]}, step=trainer.global_step)
        if hasattr(logger, "run_id") and trainer.is_global_zero:  # MLflow: the run says why it ended
            try:
                logger.experiment.set_tag(logger.run_id, "stop_reason", kind)
                logger.experiment.set_tag(logger.run_id, "stop_message", why[:5000])
            except Exception as error:  # an unreachable store must not lose the run's files
                log.warning("MLflow stop_reason not tagged: %s", str(error).splitlines()[0])
    if trainer.is_global_zero:  # under DDP every rank returns here; one writes
        write_json(
            output_dir / "metrics.json",
            {
                "epoch": trainer.current_epoch,
                "global_step": trainer.global_step,
                "stop_reason": kind,
                "stop_message": why,
                **metrics,
            },
        )
    log.info("stopped (%s): %s", kind, why)
    log.info("done in %.1f s: %s", metrics["time/wall_s"], {k: round(v, 4) for k, v in sorted(metrics.items())})
    return metrics


@stage_main("conf/gan", "train")
def main(cfg: DictConfig):
    metrics = train(cfg)
    # Hydra sweepers (e.g. Optuna) optimise the value returned: `optimized_metric=val/fid`.
    key = TrainRun.from_config(cfg).optimized_metric
    if key:
        if key not in metrics:
            raise ConfigError(f"optimized_metric={key}: not among the final metrics {sorted(metrics)}")
        return metrics[key]
    return metrics


if __name__ == "__main__":
    start(main)
