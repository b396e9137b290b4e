"""The generator starts where the images are: before the first step of a fresh run, the FCN's output biases move
so that its renders have the real patches' particle grey, background grey and background noise.

A freshly initialised FCN outputs 0.5 for every parameter (zero biases, sigmoid): each renderer value and the noise
sigma start at the middle of their limits, wherever the user's images lie inside them. The adversarial game then has
to find the grey levels before it can learn anything else, and on a small, unfamiliar set it may never get there
(on a small TEM folder, epoch 0 had the real brightness only by chance, and nothing pulled it back when it drifted).

``GreyStart`` measures three numbers on the real training patches, with the classical segmentation the patches were
mined with (the one the brightness guard of drgan.callbacks.best_epoch also uses, so "in range" means the same thing
here and there): the mean grey of particle pixels, of background pixels, and the standard deviation of the
background's high-pass residual (image minus its Gaussian blur of ``HIGHPASS_PX``: the noise and grain). It then
renders a few images per step (at ``spp``, through the same differentiable path as training), measures the same
numbers on them (masks from the same segmentation, computed without gradient; the means and the residual's
deviation are differentiable in the image) and solves for the FCN's last-layer biases only, by damped Gauss-Newton
steps on the three differences (each step the least change of the biases that zeroes them to first order, from their
Jacobian: one adjoint pass per number through the same renders), so that a bias that hardly changes the numbers hardly
moves; later steps are shortened (each step's renders are a new sample of layouts and noise, which a full step would
chase). The weights, hence the FCN's dependence on the constellation, are left as initialised. (A first-order
optimizer moves a bias with a tiny, noisy gradient at its full rate, e.g. the noise away from the real level.) It
stops after ``steps`` steps or once every number is within
``tolerance`` (grey units; the noise within NOISE_TOLERANCE of the real) for two steps in a row. Resumed runs (global step > 0) and runs started from another run's weights (``init_from``)
are left alone. What it did is logged and written to ``<run>/grey_start.json``.

**The anchor** (``anchor`` > 0, every run, resumed ones too): the generator's loss gets ``GreyAnchor``'s penalty,
zero while the render's particle and background grey lie within the range the real patches themselves span (the
best-epoch rule's brightness range), and anchor x the squared distance outside it. Why: where the scene cannot show
what the real particles look like (hollow rings against the scene's solid spheres; a film's coarse grain against a
uniform stage), the adversarial loss trades that structure against the only knobs that reach it, the grey levels,
and drifts them out of the real range for good (experiments/pipeline/README.md). The anchor leaves the game alone inside the range and stops the
trade at its edge.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch
from lightning.pytorch import Callback, LightningModule, Trainer

from drgan.callbacks.fid import brightness_tolerance, classical_masks, level_sums, real_patches, run_dir
from drgan.core.errors import ConfigError
from drgan.core.io import write_json

log = logging.getLogger(__name__)

HIGHPASS_PX = 2.0  # stddev of the blur whose residual carries the noise: grain of 1-2 px stays, shading goes
EDGE_PX = 3  # background pixels this close to a particle are left out of the noise (its edge is no noise)
CALM_STEPS = 2  # consecutive steps within tolerance that end the search
SETTLE_STEPS = 3.0  # step t is shortened to 1 / (1 + t / SETTLE_STEPS) of the Gauss-Newton step
NOISE_TOLERANCE = 0.1  # the noise counts as reached within this fraction of the real noise


def _blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B, H, W) -> the same blurred by a separable Gaussian (reflect padding)."""
    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    padded = torch.nn.functional.pad(images[:, None], (radius, radius, radius, radius), mode="reflect")
    rows = torch.nn.functional.conv2d(padded, kernel.view(1, 1, 1, -1))
    return torch.nn.functional.conv2d(rows, kernel.view(1, 1, -1, 1))[:, 0]


def grey_levels(images: torch.Tensor, particle: np.ndarray) -> dict[str, torch.Tensor]:
    """Particle grey, background grey and background noise (high-pass std) of ``images`` (B, H, W) pooled over the
    batch, with the bool ``particle`` masks (B, H, W); differentiable in ``images``. NaN where a region is empty."""
    from scipy.ndimage import binary_dilation

    particle_t = torch.as_tensor(np.asarray(particle, bool), device=images.device)
    near = np.stack([binary_dilation(m, iterations=EDGE_PX) if m.any() else m for m in np.asarray(particle, bool)])
    quiet = torch.as_tensor(~near, device=images.device)
    residual = images - _blur(images, HIGHPASS_PX)
    nan = images.new_tensor(math.nan)

    def mean(values: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        return values[where].mean() if bool(where.any()) else nan

    quiet_residual = residual[quiet]
    noise = quiet_residual.std() if quiet_residual.numel() > 1 else nan
    return {"particle": mean(images, particle_t), "background": mean(images, ~particle_t), "noise": noise}


def gauss_newton_step(jacobian: torch.Tensor, residual: torch.Tensor, max_step: float) -> torch.Tensor | None:
    """The damped Gauss-Newton (Levenberg-Marquardt) step of the biases that brings ``residual`` (m,) to zero to first
    order, given its ``jacobian`` (m, k): the least-norm solution -J^T (J J^T + lambda I)^-1 r, so that a bias that
    hardly changes the numbers hardly moves, each entry clipped to +-``max_step`` (logits; a trust region against
    the renders' noise and the sigmoid's curvature). None when the Jacobian is zero or not finite."""
    if not torch.isfinite(jacobian).all() or not torch.isfinite(residual).all():
        return None
    gram = jacobian @ jacobian.T
    scale = float(torch.diagonal(gram).mean())
    if scale <= 0:
        return None
    damping = 1e-3 * scale * torch.eye(len(residual), dtype=gram.dtype, device=gram.device)
    step = -jacobian.T @ torch.linalg.solve(gram + damping, residual)
    return step.clamp(-max_step, max_step)


class GreyAnchor:
    """A penalty on a batch of renders whose particle or background grey, measured as the brightness guard measures it
    (the classical segmentation; of the negatives for dark particles), leaves the range the real patches span: zero
    inside [low, high] of each, weight x (distance outside)^2 beyond. GANModule adds it to the generator's loss."""

    def __init__(self, segment, polarity: str, real: dict[str, float], ranges: dict, weight: float):
        self.segment, self.polarity, self.real, self.ranges, self.weight = segment, polarity, real, ranges, weight

    def ratio(self, value: torch.Tensor, key: str) -> torch.Tensor:
        real = self.real[key]
        return (1.0 - value) / (1.0 - real) if self.polarity == "dark" else value / real

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, H, W) or (B, 1, H, W), differentiable -> scalar penalty."""
        images = images.reshape(-1, *images.shape[-2:])
        levels = grey_levels(images, self.segment(images.detach().cpu().numpy()))
        penalty = images.new_zeros(())
        for key in ("particle", "background"):
            if not bool(torch.isfinite(levels[key])):
                continue
            low, high = self.ranges[key]
            ratio = self.ratio(levels[key], key)
            penalty = penalty + torch.relu(low - ratio) ** 2 + torch.relu(ratio - high) ** 2
        return self.weight * penalty


class GreyStart(Callback):
    """steps: at most this many Gauss-Newton steps; images: renders per step; lr: the largest change of a bias
    (logits) in one step;
    spp: samples per pixel of these renders (None: the training spp; grey means need few); tolerance: grey units
    within which particle and background grey count as reached (the noise: within ``NOISE_TOLERANCE`` of the real
    noise)."""

    def __init__(
        self,
        steps: int = 15,
        images: int = 2,
        lr: float = 1.5,
        spp: int | None = 16,
        tolerance: float = 0.01,
        anchor: float = 10.0,
    ):
        for name, value, low in (("steps", steps, 1), ("images", images, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"callbacks.grey_start.{name}={value!r}: expected an integer >= {low}")
        if spp is not None and (isinstance(spp, bool) or not isinstance(spp, int) or spp < 1):
            raise ConfigError(f"callbacks.grey_start.spp={spp!r}: expected an integer >= 1 or null (the training spp)")
        for name, value in (("lr", lr), ("tolerance", tolerance)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
                raise ConfigError(f"callbacks.grey_start.{name}={value!r}: expected a number > 0")
        if isinstance(anchor, bool) or not isinstance(anchor, (int, float)) or anchor < 0:
            raise ConfigError(f"callbacks.grey_start.anchor={anchor!r}: expected a weight >= 0 (0: no anchor)")
        self.steps, self.images, self.lr, self.spp, self.tolerance = steps, images, float(lr), spp, float(tolerance)
        self.anchor = float(anchor)
        self.record: dict | None = None

    def real_levels(self, trainer: Trainer) -> dict[str, float]:
        patches = real_patches(trainer)
        levels = grey_levels(torch.from_numpy(patches), classical_masks(trainer, patches))
        return {k: float(v) for k, v in levels.items()}

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if self.anchor > 0:  # resumed runs too: the anchor holds for the whole training
            self.attach_anchor(trainer, pl_module)
        if trainer.global_step > 0 or getattr(pl_module, "weights_loaded", False):
            return  # a resumed run, or one that starts from another run's weights
        if trainer.fast_dev_run:
            return
        start = time.perf_counter()
        real = self.real_levels(trainer)
        targets = {k: v for k, v in real.items() if math.isfinite(v)}
        if not {"particle", "background"} <= set(targets):
            log.warning("grey start skipped: the real patches' classical segmentation gives no %s", real)
            return
        generator = pl_module.generator
        bias = generator.regressor.net[-2].bias  # the last Linear's, before the sigmoid
        before = bias.detach().clone()
        draw = torch.Generator().manual_seed(int(getattr(pl_module, "seed", 0)))
        bank = pl_module.phi_bank
        was_training = generator.training
        generator.eval()  # no dropout: the biases answer for the network's mean output
        history, calm, first = [], 0, None
        try:
            for step in range(self.steps):
                measurement = self._measure(trainer, generator, bank, draw, step, targets, bias)
                if measurement is None:
                    continue
                measured, residual, jacobian = measurement
                first = first or measured
                history.append({"step": step, **measured, "loss": float((residual**2).sum())})
                step_vector = gauss_newton_step(jacobian, residual, self.lr)
                if step_vector is not None:  # full steps first, then shorter ones: each step's renders are a new
                    with torch.no_grad():  # sample (other layouts, other noise), and a full step would chase it
                        bias += step_vector / (1.0 + step / SETTLE_STEPS)
                calm = calm + 1 if self._reached(measured, targets) else 0
                if calm >= CALM_STEPS:
                    break
        finally:
            generator.train(was_training)
            generator.regressor.zero_grad(set_to_none=True)
        if trainer.world_size > 1:  # every rank moved the same way (same draws and seeds); rank 0 decides
            with torch.no_grad():
                bias.copy_(trainer.strategy.broadcast(bias.detach().clone(), src=0))
        last = history[-1] if history else {}
        self.record = {
            "real": real,
            "first": first,
            "last": {k: last.get(k) for k in real},
            "steps": len(history),
            "reached": calm >= CALM_STEPS,
            "bias_before": before.tolist(),
            "bias_after": bias.detach().tolist(),
            "values_after": dict(zip(pl_module.learned_keys, generator.learned_values(bank[:1].float())[0].tolist()))
            if len(bank)
            else {},
            "seconds": round(time.perf_counter() - start, 2),
            "history": history,
        }
        if trainer.is_global_zero:
            write_json(run_dir(trainer) / "grey_start.json", self.record)
            log.info(
                "grey start (%d steps, %.0f s): particle %s, background %s, noise %s (first render -> start; real)",
                len(history),
                self.record["seconds"],
                *(
                    f"{_fmt((first or {}).get(k))} -> {_fmt(last.get(k))} ({_fmt(real[k])})"
                    for k in ("particle", "background", "noise")
                ),
            )

    def _measure(self, trainer: Trainer, generator, bank, draw, step: int, targets: dict, bias):
        """One step's renders: (their grey levels, the residual against ``targets``, its Jacobian in ``bias``: one
        adjoint pass per level through the same renders), or None where no level of them is finite."""
        index = torch.randint(len(bank), (self.images,), generator=draw)
        with torch.enable_grad():
            phi = bank[index.to(bank.device)].to(generator.view_width.dtype)
            values = generator.learned_values(phi)
            seeds = [(0x5EED + step * self.images + b) & 0xFFFFFFFF for b in range(self.images)]
            images = torch.stack(
                [generator.render_one(phi[b], values[b], seed=s, spp=self.spp)[0] for b, s in enumerate(seeds)]
            )
            masks = classical_masks(trainer, images.detach().cpu().numpy())
            synthetic = grey_levels(images, masks)
            terms = {k: synthetic[k] - targets[k] for k in targets if torch.isfinite(synthetic[k])}
            if not terms:
                return None
            residual = torch.stack(list(terms.values()))
            rows = [
                torch.autograd.grad(t, bias, retain_graph=k < len(terms) - 1)[0] for k, t in enumerate(terms.values())
            ]
        measured = {k: float(v.detach()) for k, v in synthetic.items()}
        return measured, residual.detach(), torch.stack(rows)

    def attach_anchor(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Give the module its `GreyAnchor`: the real patches' grey levels and the range they span (the best-epoch
        rule's ``auto`` range, drgan.callbacks.fid.brightness_tolerance)."""
        patches = real_patches(trainer)
        masks = classical_masks(trainer, patches)
        polarity = getattr(getattr(trainer, "datamodule", None), "polarity", None) or "bright"
        real = {k: float(v) for k, v in grey_levels(torch.from_numpy(patches), masks).items()}
        ranges = brightness_tolerance(level_sums(patches, masks), polarity)
        pl_module.grey_anchor = GreyAnchor(lambda images: classical_masks(trainer, images), polarity, real, ranges,
                                           self.anchor)  # fmt: skip
        log.info("grey anchor (weight %g): particle %.2f-%.2f x, background %.2f-%.2f x of the real grey",
                 self.anchor, *ranges["particle"], *ranges["background"])  # fmt: skip

    def _reached(self, measured: dict, targets: dict) -> bool:
        for key, target in targets.items():
            value = measured.get(key, math.nan)
            allowed = NOISE_TOLERANCE * target if key == "noise" else self.tolerance
            if not abs(value - target) <= allowed:
                return False
        return True


def _fmt(value) -> str:
    return f"{value:.3f}" if isinstance(value, (int, float)) and math.isfinite(value) else "n/a"


__all__ = ["GreyAnchor", "GreyStart", "grey_levels"]
