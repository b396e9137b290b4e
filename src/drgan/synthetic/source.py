"""The trained generator a dataset is rendered from: a checkpoint file or a training run folder, the model
config saved with it, and the GANModule rebuilt from that config."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from drgan.core.errors import ConfigError


def generator_checkpoint(ckpt) -> tuple[Path, Path | None]:
    """``ckpt=``, a checkpoint file or a run folder -> (checkpoint file, run folder or None).

    A run folder means its checkpoints/best.ckpt; a file inside a run's checkpoints/ has that run folder."""
    if ckpt in (None, "", "???"):
        raise ConfigError("ckpt: expected a checkpoint file or a training run folder (with checkpoints/best.ckpt)")
    path = Path(str(ckpt)).expanduser().resolve()
    if path.is_dir():
        best = path / "checkpoints" / "best.ckpt"
        if not best.is_file():
            raise ConfigError(
                f"ckpt={ckpt}: a folder without checkpoints/best.ckpt (expected a training run folder or a .ckpt file)"
            )
        return best, path
    if not path.is_file():
        raise ConfigError(f"ckpt={ckpt}: no such checkpoint file or run folder")
    run = path.parent.parent if path.parent.name == "checkpoints" else None
    return path, run


def checkpoint_config(ckpt_file: Path) -> dict:
    """The model config (material, size, placement, renderer, model, seed) saved with a GANModule checkpoint."""
    from drgan.core.checkpoint_io import load_checkpoint

    checkpoint = load_checkpoint(ckpt_file, "ckpt", expected="a .ckpt written by drgan.train")
    cfg = (checkpoint.get("hyper_parameters") or {}).get("cfg")
    if not isinstance(cfg, dict) or "material" not in cfg:
        raise ConfigError(
            f"ckpt={ckpt_file}: no drgan model config in its hyperparameters (not a GANModule checkpoint?)"
        )
    return cfg


def effective_renderer(saved: dict, overrides) -> dict:
    """The checkpoint's renderer settings with the non-null keys of ``overrides`` (generate's renderer.*)."""
    renderer = dict(saved or {})
    given = OmegaConf.to_container(overrides) if isinstance(overrides, DictConfig) else dict(overrides or {})
    renderer.update({k: v for k, v in given.items() if v is not None})
    return renderer


def load_module(ckpt_file: Path, model_cfg: dict, material=None):
    """GANModule in eval mode, rebuilt with ``model_cfg`` (the saved one, renderer possibly overridden; ``material``:
    its material typed already)."""
    from drgan.core.checkpoint_io import refusing_unsafe
    from drgan.models.gan_module import GANModule

    with refusing_unsafe("ckpt", ckpt_file):
        module = GANModule.load_from_checkpoint(
            ckpt_file, map_location="cpu", cfg=model_cfg, weights_only=True, material=material
        )
    module.eval()
    return module


def use_parameters(module, source, model_cfg: dict, base_dir=None) -> None:
    """Make ``module`` render with the scene values of ``source``
    (`drgan.synthetic.generation_settings.parameter_source`): "trained" leaves it as loaded; "initial" gives its network
    the initial weights (the same seed and config as at the start of training); "middle" or a mapping fixes every
    learned parameter for every image."""
    import torch

    generator = module.generator
    if source == "trained":
        return
    if source == "initial":
        from drgan.models import build

        base_dir = base_dir if base_dir is not None else module.hparams["base_dir"]  # saved by every GANModule
        fresh = build.build_generator(OmegaConf.create(model_cfg), base_dir=base_dir, seed=module.seed)
        generator.regressor.load_state_dict(fresh.regressor.state_dict())
        return
    learned = generator.learned
    if source == "middle":
        values = [(p.low + p.high) / 2 for p in learned]
    else:
        keys = [p.key for p in learned]
        unknown, missing = sorted(set(source) - set(keys)), [k for k in keys if k not in source]
        if unknown or missing:
            raise ConfigError(
                f"parameters: unknown {unknown}, missing {missing}; expected a value for each learned parameter {keys}"
            )
        outside = [
            f"{p.key}={source[p.key]} not in [{p.low}, {p.high}]"
            for p in learned
            if not p.low <= source[p.key] <= p.high
        ]
        if outside:
            raise ConfigError(f"parameters: {'; '.join(outside)} (the material's limits)")
        values = [source[p.key] for p in learned]
    generator.fixed_values = torch.tensor(values, dtype=torch.float32)
