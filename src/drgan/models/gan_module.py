"""DiffRenderGAN training as a LightningModule: generator (FCN + differentiable render + noise) against
a PatchGAN discriminator, with manual optimisation.

One step renders once: ``fake = G(phi)``; D learns on ``fake.detach()`` against a real batch, then G
learns through D on the same ``fake`` (a render is by far the most expensive part of a step).
A step whose loss or gradient is not finite changes no weights (D's half of it is undone when G's half
fails); it is counted, and after
``max_consecutive_nonfinite`` such steps in a row training stops with a RuntimeError.
"""

from __future__ import annotations

import copy
import functools
import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch import LightningModule
from omegaconf import DictConfig, OmegaConf

from drgan.core.errors import ConfigError
from drgan.core.typed_settings import read_settings, setting, typed
from drgan.models import build
from drgan.scene.config import Material, typed_material

log = logging.getLogger(__name__)

# The config groups that define the model; saved with every checkpoint so that it rebuilds alone.
MODEL_GROUPS = ("material", "size", "placement", "renderer", "model", "seed")
LOSSES = ("lsgan", "vanilla")
# Render seeds of different DDP ranks must differ: rank r renders with base seed seed + r * RANK_SEED_STRIDE.
RANK_SEED_STRIDE = 7919


def model_config(cfg: DictConfig | Mapping) -> dict:
    """The part of a composed training config that the GANModule needs, resolved to plain values."""
    cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(dict(cfg))
    return {
        k: OmegaConf.to_container(cfg[k], resolve=True) if isinstance(cfg[k], DictConfig) else cfg[k]
        for k in MODEL_GROUPS
        if k in cfg
    }


@typed
@dataclass
class LRDecay:
    """Learning-rate factor per training step (``model.lr_decay``): 1 until ``start_step``, then linear down to
    ``final_factor`` over ``steps`` steps, then constant (pix2pix decays linearly too, over its second half); 1 at every
    step when ``start_step`` is null. Applied to G and D.

    A plain callable object, not a lambda, so that the schedulers' state pickles into checkpoints."""

    start_step: int | None = setting(ge=0)
    steps: int = setting(300, ge=1)
    final_factor: float = setting(0.1, ge=0.0, le=1.0)

    def __post_init__(self):
        if (self.start_step is not None and self.start_step < 0) or self.steps < 1 or not 0 <= self.final_factor <= 1:
            raise ConfigError(
                f"model.lr_decay: start_step={self.start_step}, steps={self.steps}, final_factor={self.final_factor}: "
                "expected start_step >= 0, steps >= 1 and final_factor in [0, 1]"
            )

    @classmethod
    def from_config(cls, cfg: Mapping | None, stage: str = "train") -> LRDecay | None:
        """The decay ``model.lr_decay`` sets; None (constant learning rates, no scheduler) when ``cfg`` or its
        ``start_step`` is null."""
        if not cfg:
            return None
        decay = read_settings(cls, {"start_step": None, **cfg}, stage, prefix="model.lr_decay.")
        return None if decay.start_step is None else decay

    def __call__(self, step: int) -> float:
        if self.start_step is None:
            return 1.0
        progress = min(max(step - self.start_step, 0) / self.steps, 1.0)
        return 1.0 - (1.0 - self.final_factor) * progress


def _adam(lr: float):
    return functools.partial(torch.optim.Adam, lr=lr, betas=(0.5, 0.999))


def _optimizer(net: str):
    """`read_settings`'s check of ``model.optimizer_<net>``: the factory its ``_target_``/``_partial_`` config builds."""
    return lambda stage, spec: build.optimizer_factory(spec, f"model.optimizer_{net}")


@dataclass(frozen=True)
class GANTraining:
    """How the two networks learn (``conf/gan/model``): adversarial loss, the two optimisers (factories
    ``parameters -> optimizer``, from the ``_target_``/``_partial_`` configs ``model.optimizer_g``/``optimizer_d``),
    the optional learning-rate decay, and how many non-finite steps in a row stop training."""

    loss: str = "lsgan"
    optimizer_g: Callable = field(default_factory=lambda: _adam(2e-4), metadata={"check": _optimizer("g")})
    optimizer_d: Callable = field(default_factory=lambda: _adam(1e-4), metadata={"check": _optimizer("d")})
    lr_decay: LRDecay | None = field(default=None, metadata={"check": lambda stage, v: LRDecay.from_config(v, stage)})
    max_consecutive_nonfinite: int = 5

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ConfigError(f"model.loss={self.loss!r}: expected one of {LOSSES}")
        if self.max_consecutive_nonfinite < 1:
            raise ConfigError(f"model.max_consecutive_nonfinite={self.max_consecutive_nonfinite}: expected >= 1")

    @property
    def lr_g(self) -> float | None:
        return getattr(self.optimizer_g, "keywords", {}).get("lr")

    @property
    def lr_d(self) -> float | None:
        return getattr(self.optimizer_d, "keywords", {}).get("lr")

    @classmethod
    def from_config(cls, model: Mapping | None, stage: str = "train") -> GANTraining:
        """From the ``model`` group (`drgan.core.typed_settings.read_settings`); absent keys take the defaults above."""
        return read_settings(cls, model, stage, prefix="model.")


class GANModule(LightningModule):
    """The GAN from built parts, as Lightning modules of the lightning-hydra-template take theirs:

    generator: `drgan.models.generator.Generator` (FCN + scene + noise); discriminator: `PatchDiscriminator`;
    layouts: ``layouts(m, seed) -> (m, n, 4)`` constellations (`drgan.models.build.LayoutSampler`); training:
    `GANTraining`; texture_highpass_px: the stage texture's high-pass width, None for an untextured material;
    m: constellations in the phi bank (None: drawn later with `set_constellations`); seed: phi bank, phi
    order and render seeds. ``config`` is what rebuilds the same module from a checkpoint (`from_config`'s input:
    the model config and base_dir); `from_config` fills it, a module built by hand may leave it out (and then
    cannot be loaded with `load_from_checkpoint`).
    """

    def __init__(
        self,
        generator: torch.nn.Module,
        discriminator: torch.nn.Module | None = None,
        layouts=None,
        training: GANTraining | None = None,
        *,
        texture_highpass_px: float | None = None,
        m: int | None = None,
        seed: int = 0,
        config: Mapping | None = None,
    ):
        if isinstance(generator, (Mapping, DictConfig)):
            raise TypeError(
                "GANModule(generator, discriminator, layouts, ...) takes built parts; "
                "from a config: GANModule.from_config(cfg, m=None, base_dir=None)"
            )
        if discriminator is None or layouts is None:
            raise TypeError("GANModule: discriminator and layouts are required (or build all parts with from_config)")
        super().__init__()
        self.automatic_optimization = False
        config = dict(config or {})
        self.save_hyperparameters({"cfg": config.get("cfg"), "m": m, "base_dir": config.get("base_dir")}, logger=False)
        training = training if training is not None else GANTraining()
        self.seed = int(seed)
        self.loss_kind = training.loss
        self.optimizer_g, self.optimizer_d = training.optimizer_g, training.optimizer_d
        self.lr_g, self.lr_d = training.lr_g, training.lr_d
        self.lr_decay = training.lr_decay
        self.max_consecutive_nonfinite = training.max_consecutive_nonfinite
        self.layouts = layouts
        self.texture_highpass_px = texture_highpass_px

        self.generator = generator
        self.discriminator = discriminator
        self.discriminator.check_size(self.generator.scene.spec.render.resolution)

        # The phi bank: m constellations drawn once. m defaults to the number of training patches, known only
        # after mining, so drgan.train builds (and so checks) the module first and calls set_constellations later.
        self.register_buffer("phi_bank", torch.zeros(0, self.generator.scene.n_particles, 4))
        if m is not None:
            self.set_constellations(m)
        # phi indices come from a generator of their own (per rank, saved in checkpoints), not the global RNG.
        self.phi_rng = torch.Generator().manual_seed(self.seed)
        self.skipped_steps = 0
        self.consecutive_nonfinite = 0
        self.weights_loaded = False  # True after load_weights (init_from): its FCN is not re-started at the real grey
        # images (B, 1, H, W) -> a penalty added to the generator's loss (drgan.callbacks.grey_start.GreyAnchor gives
        # one: it keeps the renders' grey within the range the real patches span); None: the adversarial loss alone
        self.grey_anchor = None

    @classmethod
    def from_config(
        cls,
        cfg: DictConfig | Mapping,
        m: int | None = None,
        base_dir: str | Path | None = None,
        material: Material | None = None,
    ) -> GANModule:
        """The module of a composed config (or its ``model_config``): scene, generator and discriminator built
        by `drgan.models.build` (generator first: both draw their initial weights from torch's seeded RNG);
        m: constellations in the phi bank (default: ``model.n_constellations``, else set later); ``material``:
        ``cfg.material`` typed already (else typed here, once)."""
        plain = model_config(cfg)
        cfg = OmegaConf.create(plain)
        model = cfg.get("model") or OmegaConf.create({})
        seed = int(cfg.get("seed", 0))
        material = typed_material(cfg.material if material is None else material)
        training = GANTraining.from_config(OmegaConf.to_container(model))
        generator = build.build_generator(cfg, base_dir=base_dir, seed=seed, material=material)
        discriminator = build.build_discriminator(model)
        m = m if m is not None else model.get("n_constellations")
        return cls(
            generator,
            discriminator,
            build.layout_sampler(cfg, material),
            training,
            texture_highpass_px=material.texture_highpass_px,
            m=m,
            seed=seed,
            config={"cfg": plain, "base_dir": None if base_dir is None else str(base_dir)},
        )

    @classmethod
    def load_from_checkpoint(
        cls,
        checkpoint_path,
        map_location=None,
        hparams_file=None,
        strict=True,
        cfg=None,
        weights_only=True,
        material: Material | None = None,
        **kwargs,
    ) -> GANModule:
        """The module of a drgan.train checkpoint, rebuilt with `from_config` from the config saved in it (or
        ``cfg``, e.g. with another renderer), then its weights, phi bank and step state. Loaded with
        ``weights_only=True`` always (`drgan.core.checkpoint_io`): a checkpoint holding code is refused unread."""
        from drgan.core.checkpoint_io import load_checkpoint

        if hparams_file is not None or kwargs:
            raise TypeError(f"GANModule.load_from_checkpoint: unsupported arguments {['hparams_file', *kwargs]}")
        path = Path(checkpoint_path)
        checkpoint = load_checkpoint(path, "ckpt", expected="a .ckpt written by drgan.train")
        hparams = checkpoint.get("hyper_parameters") or {}
        config = cfg if cfg is not None else hparams.get("cfg")
        if config is None:
            raise ConfigError(
                f"ckpt={path}: no model config in its hyperparameters (a GANModule built by hand, or not a GANModule "
                "checkpoint); pass cfg= to rebuild it"
            )
        module = cls.from_config(config, m=hparams.get("m"), base_dir=hparams.get("base_dir"), material=material)
        module.on_load_checkpoint(checkpoint)
        module.load_state_dict(checkpoint["state_dict"], strict=strict)
        return module if map_location is None else module.to(map_location)

    def set_constellations(self, m: int) -> None:
        """Draw the phi bank of ``m`` constellations (seeded by ``seed``); saved with the hyperparameters."""
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or int(m) < 1:
            raise ConfigError(
                f"model.n_constellations={m!r}: expected an integer >= 1 (default: the number of training patches)"
            )
        self.phi_bank = torch.as_tensor(self.sample_phi(int(m), seed=self.seed), dtype=torch.float32)
        self.hparams["m"] = int(m)  # load_from_checkpoint rebuilds a bank of this size

    def sample_phi(self, m: int, seed: int) -> np.ndarray:
        """``m`` constellations (m, n, 4) from this module's size and placement distributions, seeded by ``seed``:
        what callbacks draw their fixed evaluation sets from."""
        return self.layouts(int(m), seed=int(seed))

    @property
    def learned_keys(self) -> list[str]:
        return [p.key for p in self.generator.learned]

    def setup(self, stage: str) -> None:
        rank = int(self.global_rank)
        self.generator.base_seed = self.seed + RANK_SEED_STRIDE * rank
        self.phi_rng.manual_seed(self.seed + RANK_SEED_STRIDE * rank)
        if self.textured:
            self.use_background_texture(getattr(getattr(self.trainer, "datamodule", None), "background_patches", None))

    @property
    def textured(self) -> bool:
        """Whether the material adds real background texture to the stage (``material.background_texture``)."""
        return self.texture_highpass_px is not None

    def use_background_texture(self, patches) -> None:
        """Give the generator its stage texture from real background patches (k, H, W). Training does this in
        ``setup``; a module loaded from a checkpoint for rendering needs it from the run's ``patches/``."""
        self.generator.set_background(build.make_background_texture(self.texture_highpass_px, patches))

    # --- optimisers and losses ----------------------------------------------------------------------------

    def configure_optimizers(self):
        opt_g = self.optimizer_g(self.generator.parameters())
        opt_d = self.optimizer_d(self.discriminator.parameters())
        if self.lr_decay is None:
            return [opt_g, opt_d]
        # Stepped once per training step in training_step (manual optimisation steps schedulers by hand).
        schedulers = [torch.optim.lr_scheduler.LambdaLR(opt, self.lr_decay) for opt in (opt_g, opt_d)]
        return [opt_g, opt_d], schedulers

    def adversarial_loss(self, logits: torch.Tensor, real: bool) -> torch.Tensor:
        target = torch.full_like(logits, 1.0 if real else 0.0)
        if self.loss_kind == "lsgan":
            return F.mse_loss(logits, target)
        return F.binary_cross_entropy_with_logits(logits, target)

    def score(self, logits: torch.Tensor) -> torch.Tensor:
        """D's mean verdict: raw output (LSGAN, target 1 real / 0 fake) or probability of real (vanilla)."""
        return (logits if self.loss_kind == "lsgan" else torch.sigmoid(logits)).mean()

    # --- the step -----------------------------------------------------------------------------------------

    def draw_phi(self, batch_size: int) -> torch.Tensor:
        if len(self.phi_bank) == 0:
            raise RuntimeError("GANModule: no phi bank yet; call set_constellations(m) before training")
        index = torch.randint(len(self.phi_bank), (batch_size,), generator=self.phi_rng)
        return self.phi_bank[index.to(self.phi_bank.device)]

    def render(self, phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, n, 4) -> images (B, 1, H, W) and the learned values (B, k) used for them."""
        images, values = self.generator.render_batch(phi)
        return images.to(self.device), values

    @staticmethod
    def _finite_grads(module: torch.nn.Module) -> bool:
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        return all(bool(torch.isfinite(g).all()) for g in grads)

    def _optimise(self, optimizer, module: torch.nn.Module, compute_loss) -> tuple[bool, torch.Tensor]:
        """One guarded update of ``module``: (False, loss) and no step when the loss or a gradient is not finite.

        ``compute_loss()`` runs inside the optimizer's toggle, where only ``module``'s parameters require
        gradients: the G loss's pass through D then builds no graph for D's weights, and the backward computes
        only what G needs (D's input gradient), not D's weight gradients, which G's step would discard."""
        self.toggle_optimizer(optimizer)
        try:
            optimizer.zero_grad(set_to_none=True)
            loss = compute_loss()
            if not torch.isfinite(loss).all():
                return False, loss
            self.manual_backward(loss)
            if not self._finite_grads(module):
                optimizer.zero_grad(set_to_none=True)
                return False, loss
            optimizer.step()
            return True, loss
        finally:
            self.untoggle_optimizer(optimizer)

    def training_step(self, batch, batch_idx):
        start = time.perf_counter()
        real = batch if torch.is_tensor(batch) else batch[0]
        opt_g, opt_d = self.optimizers()
        phi = self.draw_phi(real.shape[0])

        render_start = time.perf_counter()
        fake, values = self.render(phi)
        render_s = time.perf_counter() - render_start

        # D: real -> 1, detached fake -> 0. G: fake through the (just updated) D -> 1.
        # D learns first, so a step whose G half fails must undo D's half: D (weights, batch-norm statistics) and
        # its optimiser state are kept until the step is known to be good.
        d_before = _snapshot(self.discriminator, opt_d)
        logits = {}

        def d_loss_of():
            logits["real"], logits["fake"] = self.discriminator(real), self.discriminator(fake.detach())
            return 0.5 * (self.adversarial_loss(logits["real"], True) + self.adversarial_loss(logits["fake"], False))

        ok, d_loss = self._optimise(opt_d, self.discriminator, d_loss_of)
        g_loss = torch.tensor(float("nan"))
        anchored = {}

        def g_loss_of():
            loss = self.adversarial_loss(self.discriminator(fake), True)
            if self.grey_anchor is not None:
                anchored["penalty"] = self.grey_anchor(fake)
                loss = loss + anchored["penalty"]
            return loss

        if ok:  # a failed D step skips the whole step: G would learn against a broken verdict
            ok, g_loss = self._optimise(opt_g, self.generator, g_loss_of)
        if not ok:
            _restore(self.discriminator, opt_d, d_before)
        self._count(ok, d_loss, g_loss)
        if self.lr_decay is not None:  # per training step, skipped ones included: the schedule follows the step count
            for scheduler in self.lr_schedulers():  # [G's, D's]
                scheduler.step()

        # Step values under their plain names (train/g_loss ...), epoch means as <name>_epoch.
        scalars = {
            "train/skipped_steps": float(self.skipped_steps),
            "time/render_s": render_s,
            "train/lr_g": opt_g.param_groups[0]["lr"],
        }
        if ok:
            scalars.update({
                "train/d_loss": d_loss.detach(),
                "train/g_loss": g_loss.detach(),
                "train/d_real": self.score(logits["real"].detach()),
                "train/d_fake": self.score(logits["fake"].detach()),
            })  # fmt: skip
            scalars.update({f"params/{k}": v for k, v in zip(self.learned_keys, values.detach().mean(0).tolist())})
            if "penalty" in anchored:
                scalars["train/grey_penalty"] = anchored["penalty"].detach()
        scalars["time/step_s"] = time.perf_counter() - start
        self.log_scalars(scalars, real.shape[0])

    def log_scalars(self, scalars: dict, batch_size: int) -> None:
        for key, value in scalars.items():
            self.log(
                key,
                value,
                on_step=True,
                on_epoch=False,
                prog_bar=key in ("train/d_loss", "train/g_loss"),
                batch_size=batch_size,
            )
            if key != "train/skipped_steps":
                # Epoch means over all DDP ranks (one reduction per epoch; a no-op in a single process).
                self.log(f"{key}_epoch", value, on_step=False, on_epoch=True, batch_size=batch_size, sync_dist=True)

    def _count(self, ok: bool, d_loss: torch.Tensor, g_loss: torch.Tensor) -> None:
        if ok:
            self.consecutive_nonfinite = 0
            return
        self.skipped_steps += 1
        self.consecutive_nonfinite += 1
        log.warning(
            "step %d skipped: non-finite loss or gradient (d_loss=%s, g_loss=%s); %d in a row, %d in all",
            self.global_step, _fmt(d_loss), _fmt(g_loss), self.consecutive_nonfinite, self.skipped_steps,
        )  # fmt: skip
        if self.consecutive_nonfinite >= self.max_consecutive_nonfinite:
            raise RuntimeError(
                f"training stopped: {self.consecutive_nonfinite} steps in a row had a non-finite loss or gradient "
                f"(model.max_consecutive_nonfinite={self.max_consecutive_nonfinite}; {self.skipped_steps} skipped in all). "
                "Try lower learning rates (model.lr_g, model.lr_d), narrower parameter limits in the material config "
                "(material.imaging.* / material.noise_sigma), or a different renderer.integrator."
            )

    # --- for callbacks and inference ----------------------------------------------------------------------

    @torch.no_grad()
    def parameter_samples(self, phi) -> np.ndarray:
        """Learned parameter values (B, k), in ``learned_keys`` order, for constellations (B, n, 4); eval mode."""
        phi = torch.as_tensor(np.asarray(phi) if not torch.is_tensor(phi) else phi, dtype=torch.float32)
        if phi.dim() == 2:
            phi = phi.unsqueeze(0)
        was_training = self.generator.training
        self.generator.eval()
        try:
            return self.generator.learned_values(phi.to(self.phi_bank.device)).cpu().numpy()
        finally:
            self.generator.train(was_training)

    # --- warm start -----------------------------------------------------------------------------------------

    WARM_START_PREFIXES = ("generator.regressor.", "discriminator.")

    def load_weights(self, path: str | Path) -> int:
        """Copy the FCN and discriminator weights of another run's checkpoint (``init_from``) into this module.

        Only the networks: the phi bank, the render counter, optimiser state and the epoch count stay those of
        the new run, which starts at epoch 0. Every tensor must exist with the same shape; the FCN's input
        width is 4 x material.n_particles, its output the number of learned parameters. Returns the number
        of tensors copied.
        """
        from drgan.core.checkpoint_io import load_checkpoint

        path = Path(path)
        source = load_checkpoint(path, "init_from", expected="a .ckpt written by drgan.train")["state_dict"]
        target = {k: v for k, v in self.state_dict().items() if k.startswith(self.WARM_START_PREFIXES)}
        missing = sorted(set(target) - set(source))
        if missing:
            raise ConfigError(
                f"init_from={path}: the checkpoint lacks {missing[:3]}{' ...' if len(missing) > 3 else ''}"
            )
        for key, value in target.items():
            if source[key].shape != value.shape:
                raise ConfigError(
                    f"init_from={path}: {key} has shape {tuple(source[key].shape)} there and {tuple(value.shape)} here; "
                    "the FCN's input is 4 x material.n_particles wide and its output is one per learned parameter, "
                    "so both runs need the same n_particles and learned parameters (and the same discriminator settings)"
                )
        with torch.no_grad():
            for key, value in target.items():
                value.copy_(source[key])
        self.weights_loaded = True
        return len(target)

    # --- checkpoint state beyond the weights --------------------------------------------------------------

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["drgan"] = {
            "phi_rng_state": self.phi_rng.get_state(),
            "skipped_steps": self.skipped_steps,
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        state = checkpoint.get("drgan") or {}
        if "phi_rng_state" in state:
            self.phi_rng.set_state(state["phi_rng_state"])
        self.skipped_steps = int(state.get("skipped_steps", 0))


def _raw_optimizer(optimizer) -> torch.optim.Optimizer:
    return getattr(optimizer, "optimizer", optimizer)  # Lightning wraps optimisers in LightningOptimizer


def _snapshot(module: torch.nn.Module, optimizer) -> tuple[dict, dict]:
    """Copies of a module's state (parameters and buffers) and of its optimiser's state, for ``_restore``."""
    state = {k: v.detach().clone() for k, v in module.state_dict().items()}
    return state, copy.deepcopy(_raw_optimizer(optimizer).state_dict())


def _restore(module: torch.nn.Module, optimizer, snapshot: tuple[dict, dict]) -> None:
    state, optimizer_state = snapshot
    with torch.no_grad():
        for key, value in module.state_dict().items():
            value.copy_(state[key])
    _raw_optimizer(optimizer).load_state_dict(optimizer_state)


def _fmt(value: torch.Tensor) -> str:
    v = float(value.detach().float().mean()) if torch.is_tensor(value) else float(value)
    return f"{v:.4g}" if math.isfinite(v) else str(v)
