"""FID and KID of the generator against the real training patches, once per epoch.

At the end of a training epoch the generator renders as many images as there are real training patches
(from the module's phi bank, cycling when the bank is smaller), without gradients, and compares their
Inception features with those of the real patches. The real statistics are cached on disk, keyed by a hash
of the patch array and its resolution, so a resumed run or a second run on the same patches skips them.

Also the *brightness*: mean grey of the synthetic images / mean grey of the real patches. The FID hardly
sees a global change of brightness (the real TiO2 SEM patches x 0.25 score 57.7 against themselves, while
a generator 4-5x too dark gives useless segmentation data), so the best-epoch rule checks it separately, for
particles and background apart: ``val/particle_brightness`` and ``val/background_brightness`` (synthetic / real
mean grey of particle pixels, of background pixels; on both sides the pixels come from the classical
segmentation the patches were mined with, so that its bias cancels (the exact labels where it finds no particle
in any synthetic image); for dark particles the ratio of the negatives, `level_ratio`), and ``val/contrast``
(particle / background of the synthetic images from their exact labels, in the data's direction, `contrast`:
below 1 the contrast is inverted). A whole-image mean misses an epoch whose particles are brighter than a dark-
particle stage. Why the same segmentation on both sides: a threshold keeps the bright part of a particle and
leaves its shaded rim and interior to the background, so exact labels against thresholded real pixels read a
TiO2 SEM epoch with darker particle interiors as 0.53x real where the like-for-like ratio is 0.67x
(experiments/early_stop/README.md).

**How far off is too far** (``brightness_tolerance``, for ``callbacks.best_epoch.brightness_range: auto``, the
default): as far as the real training patches themselves spread. Each real patch's own particle grey and background
grey (the same classical segmentation) is divided by the real grey the synthetic one is compared with
(``real_levels``, pooled over the patches; for dark particles the negatives, as in ``level_ratio``); the allowed
range is the 5th-95th percentile of these ratios, widened to at least 1/1.1-1.1x. Why these numbers: an epoch's
grey is a mean over as many images as there are real patches, far steadier than one patch, so a mean grey that
fewer than 5 % of the real patches reach is off in its images as a whole, not by chance; relative to the pooled
real grey (not the median patch) the range is literally the band of grey the real patches span; the floor (a
set choice, not a measurement) keeps a very uniform real set, all patches within a few % of each other, from
leaving a band no generator hits. On the TiO2 patches as ``drgan.train`` mines them (``patches/patches.npz``,
train) the range is particles 0.75-1.26x and background 0.57-1.35x for SEM (134 patches, bright particles; its
near-black background varies most), particles 0.91-1.10x (the floor; the real ones span 0.95-1.03x) and
background 0.70-1.60x for TSEM (126 patches, dark particles, negatives: the bare film's grey varies from image to
image). The old fixed 0.5-2x let through a background 0.62x real.

**The FID's own spread** (``fid_resamples``, default 10): each full evaluation also records ``fid_std``, the std
of the FID over bootstrap resamples of the generated features (``drgan.metrics.feature_distances.fid_bootstrap_std``,
seeded by the epoch; 0.2-0.4 s at 2048 Inception features and ~130 images), which the best-epoch rule weighs FID
differences against.

Logged: ``val/fid``, ``val/fid_std``, ``val/kid`` (mean over subsets), the brightness values and ``time/fid_s``,
through ``pl_module.log`` so that a ``ModelCheckpoint(monitor="val/fid")`` sees them. The per-epoch history
travels in the checkpoint.

**The screen** (``screen_images``, e.g. 48): an evaluation first renders only the first ``screen_images`` of its
images and scores them with KID (unbiased at any sample size, unlike FID); only an epoch whose screen KID is at
most (1 + ``screen_margin``) x the lowest screen KID so far goes on to the full FID, rendering the remaining
images (the screen's images are the first of the full set, same seeds: the full FID is the one the callback
computes without a screen). An epoch screened out logs ``val/fid`` = NaN (never the best; an early-stopping
patience counts it as no improvement; ``TrainingProgressBar`` shows it as "screened") and ``val/screen_kid``. It saves most of the evaluation where a run has
stopped improving, which is where an early stop needs its evaluations (experiments/early_stop/).
"""

from __future__ import annotations

import hashlib
import logging
import math
import shutil
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from lightning.pytorch import Callback, LightningModule, Trainer

from drgan.core.errors import ConfigError, check_spp
from drgan.core.io import write_with
from drgan.metrics.feature_distances import FeatureStats, cached_reference_stats, fid_bootstrap_std, kid
from drgan.metrics.inception import InceptionFeatures

log = logging.getLogger(__name__)

# FID renders use seeds of their own, far from the training seeds, so they do not touch the generator's
# render counter (saved in checkpoints) and an epoch's FID images are reproducible.
FID_SEED_BASE = 0x5EED0000

# The derived brightness tolerance (``brightness_tolerance``): the 5th-95th percentile of the real patches' own
# particle and background greys / the real grey, widened to at least 1/1.1-1.1.
BRIGHTNESS_PERCENTILES = (5.0, 95.0)
BRIGHTNESS_FLOOR = 1.1


# --- helpers shared by the drgan callbacks --------------------------------------------------------------------


def run_dir(trainer: Trainer) -> Path:
    """The run folder: the trainer's default_root_dir (conf/gan/trainer sets it to paths.output_dir)."""
    return Path(trainer.default_root_dir)


def checkpoint_dir(trainer: Trainer) -> Path:
    """Where ModelCheckpoint writes (``<run>/checkpoints`` by default)."""
    callback = getattr(trainer, "checkpoint_callback", None)
    dirpath = getattr(callback, "dirpath", None)
    return Path(dirpath) if dirpath else run_dir(trainer) / "checkpoints"


def atomic_copy(src: Path, dst: Path) -> None:
    """Copy to a temp file beside ``dst``, then rename: a reader never sees half a file."""
    with open(src, "rb") as source:
        write_with(dst, lambda handle: shutil.copyfileobj(source, handle))


def mlflow_loggers(trainer: Trainer) -> list:
    from lightning.pytorch.loggers import MLFlowLogger

    return [lg for lg in trainer.loggers if isinstance(lg, MLFlowLogger)]


def log_artifact(trainer: Trainer, path: Path, artifact_path: str | None = None) -> None:
    """Log a file as an artifact of the run's MLflow run (rank 0 only; no-op without an MLflow logger)."""
    if not trainer.is_global_zero:
        return
    for logger in mlflow_loggers(trainer):
        try:
            logger.experiment.log_artifact(logger.run_id, str(path), artifact_path)
        except Exception as error:  # an unreachable artifact store must not stop training
            log.warning("MLflow artifact %s not logged: %s", path, str(error).splitlines()[0])


def real_patches(trainer: Trainer) -> np.ndarray:
    datamodule = getattr(trainer, "datamodule", None)
    patches = getattr(datamodule, "real_patches", None)
    if patches is None:
        raise ConfigError("FID callbacks need a datamodule with real_patches (drgan.data.RealPatchDataModule)")
    return np.asarray(patches, dtype=np.float32)


def dataset_key(patches: np.ndarray) -> str:
    """Cache key of a patch set: a hash of its bytes and shape (the resolution is added by the cache)."""
    digest = hashlib.sha1(np.ascontiguousarray(patches).tobytes())
    digest.update(str(patches.shape).encode())
    return f"real_{digest.hexdigest()[:16]}"


def render_samples(
    pl_module: LightningModule,
    n: int,
    seed_base: int,
    progress: bool = False,
    spp: int | None = None,
    indices: Sequence[int] | None = None,
    masks: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Images (len, H, W) in [0, 1] without gradients: image i uses constellation ``i % len(phi_bank)`` and
    seed ``seed_base + i``, so it is the same whichever process renders it. ``indices`` None: 0 .. n-1;
    ``spp`` None renders at the training spp. ``masks``: also return their particle masks (len, H, W) bool."""
    bank = pl_module.phi_bank
    iterator = range(n) if indices is None else list(indices)
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc="FID renders", unit="img", leave=False)
    samples = [
        pl_module.generator.sample(bank[i % len(bank)].cpu(), seed=(seed_base + i) & 0xFFFFFFFF, spp=spp)
        for i in iterator
    ]
    images = np.clip(np.stack([s.image for s in samples]).astype(np.float32), 0.0, 1.0)
    return (images, np.stack([s.labels > 0 for s in samples])) if masks else images


def level_sums(images: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Per image (len, 4): sum and count of particle pixels, sum and count of background pixels."""
    images, masks = np.asarray(images, dtype=np.float64), np.asarray(masks, dtype=bool)
    return np.stack(
        [
            (images * masks).sum(axis=(1, 2)),
            masks.sum(axis=(1, 2)),
            (images * ~masks).sum(axis=(1, 2)),
            (~masks).sum(axis=(1, 2)),
        ],
        axis=1,
    )


def classical_masks(trainer: Trainer, images: np.ndarray) -> np.ndarray:
    """Particle pixels (len, H, W) bool of ``images`` as the datamodule's patch mining sees them: its classical
    segmentation (``data.segment``) in its polarity. Applied alike to real and synthetic images."""
    from drgan.data.classical import particle_foreground

    datamodule = getattr(trainer, "datamodule", None)
    polarity, segment = getattr(datamodule, "polarity", None) or "bright", getattr(datamodule, "segment", None)
    return np.stack([particle_foreground(image, segment, polarity) for image in images])


def levels(sums: np.ndarray) -> tuple[float, float]:
    """(mean particle grey, mean background grey) over every image of ``level_sums`` rows (NaN when absent)."""
    total = np.asarray(sums, dtype=np.float64).sum(axis=0)
    return (float(total[0] / total[1]) if total[1] else math.nan), (
        float(total[2] / total[3]) if total[3] else math.nan
    )


def level_ratio(synthetic: float, real: float, polarity: str) -> float:
    """Synthetic / real grey level, in the data's polarity: of the negatives (1 - grey) for dark particles, whose
    levels near black would make a plain ratio explode (real TSEM particles 0.03, a synthetic 0.08: 2.7x, though
    both read as black; as negatives 0.92 / 0.97)."""
    if polarity == "dark":
        synthetic, real = 1.0 - synthetic, 1.0 - real
    return float(synthetic / real) if real > 0 else math.nan


def brightness_tolerance(
    sums: np.ndarray,
    polarity: str,
    percentiles: tuple[float, float] = BRIGHTNESS_PERCENTILES,
    floor: float = BRIGHTNESS_FLOOR,
) -> dict[str, list[float]]:
    """The brightness range the real patches themselves span: ``level_sums`` rows of the real patches (their
    classical segmentation) -> {"particle": [low, high], "background": [low, high]}, each the ``percentiles``
    (numpy's linear interpolation) of the per-patch grey / the pooled real grey (``levels`` of all rows, the
    reference of ``val/particle_brightness`` and ``val/background_brightness``; ``level_ratio``: for dark
    particles of the negatives), widened to at least [1 / floor, floor]. Patches without particle (or
    background) pixels do not count for that range; with none at all it is [1 / floor, floor]."""
    sums = np.asarray(sums, dtype=np.float64).reshape(-1, 4)
    reference = levels(sums)
    ranges = {}
    for name, (total, count), real in zip(("particle", "background"), ((0, 1), (2, 3)), reference):
        have = sums[:, count] > 0
        ratios = np.array([level_ratio(g, real, polarity) for g in sums[have, total] / sums[have, count]])
        ratios = ratios[np.isfinite(ratios)]
        low, high = np.percentile(ratios, percentiles) if ratios.size else (1.0, 1.0)
        ranges[name] = [float(min(low, 1.0 / floor)), float(max(high, floor))]
    return ranges


def contrast(particle: float, background: float, polarity: str) -> float:
    """How far particles stand out in the data's direction: particle / background for bright particles,
    background / particle for dark ones; above 1 when they lie on the right side of the background."""
    ratio = particle / background if polarity == "bright" else background / particle
    return float(ratio) if math.isfinite(ratio) else math.nan


def training_steps(trainer: Trainer) -> int:
    """Training iterations done (batches): ``trainer.global_step`` counts optimizer steps, two per iteration here."""
    return int(trainer.fit_loop.epoch_loop.batch_progress.total.completed)


def rank_share(n: int, rank: int, world: int) -> list[int]:
    """Image indices rendered by ``rank`` of ``world``: rank, rank + world, ... (ceil(n / world) of them, so
    that every rank renders as many; indices >= n are padding, dropped after the gather)."""
    return [rank + world * j for j in range(math.ceil(n / world))]


def gather_rows(trainer: Trainer, rows: np.ndarray, n: int) -> np.ndarray:
    """Every rank's ``rows`` (one per index of its ``rank_share``) in index order 0 .. n-1, on every rank."""
    if trainer.world_size == 1:
        return rows[:n]
    gathered = trainer.strategy.all_gather(torch.as_tensor(np.ascontiguousarray(rows), dtype=torch.float64))
    gathered = gathered.cpu().numpy()  # (world, per_rank, ...): index rank + world * j sits at [rank, j]
    return np.swapaxes(gathered, 0, 1).reshape(-1, *rows.shape[1:])[:n]


class RandomProjectionFeatures:
    """A fast stand-in for the Inception network, for tests and smoke runs: a fixed random projection of
    the flattened pixels to ``dim`` features. Its "FID" is NOT comparable with a real FID."""

    def __init__(self, dim: int = 32, seed: int = 0):
        self.dim, self.seed = int(dim), int(seed)

    def features(self, images: np.ndarray) -> np.ndarray:
        flat = np.asarray(images, dtype=np.float64).reshape(len(images), -1)
        proj = np.random.default_rng(self.seed).standard_normal((flat.shape[1], self.dim)) / np.sqrt(flat.shape[1])
        return flat @ proj


# --- the callback -------------------------------------------------------------------------------------------


class FIDCallback(Callback):
    """every_n_epochs: evaluate every n-th epoch (and never on others); n_images: synthetic images per
    evaluation (None: as many as real training patches); batch_size: Inception batch size; cache_dir: real
    statistics cache (None: ``<run>/fid_cache``); extractor: an object with ``features(images) -> (N, D)``
    (None: the TF-Inception network); kid_subsets/kid_subset_size: KID's random subsets (size None: half the smaller
    of the synthetic and real samples, see ``drgan.metrics.feature_distances.kid``); spp: samples per
    pixel of the FID renders (None: the training spp; fix it to compare runs trained at different spp);
    screen_images / screen_margin: the KID screen of the module docstring (None: every evaluation is a full FID);
    fid_resamples: bootstrap resamples for ``fid_std`` (0: none, and the best-epoch rule falls back to a fixed
    margin)."""

    def __init__(
        self,
        every_n_epochs: int = 1,
        n_images: int | None = None,
        batch_size: int = 16,
        cache_dir: str | None = None,
        extractor=None,
        kid_subsets: int = 100,
        kid_subset_size: int | None = None,
        progress: bool = True,
        spp: int | None = None,
        screen_images: int | None = None,
        screen_margin: float = 0.2,
        fid_resamples: int = 10,
    ):
        if int(every_n_epochs) < 1:
            raise ConfigError(f"FIDCallback.every_n_epochs={every_n_epochs}: expected >= 1")
        if n_images is not None and int(n_images) < 2:
            raise ConfigError(f"FIDCallback.n_images={n_images}: expected >= 2 (a covariance needs two images) or null")
        self.every_n_epochs = int(every_n_epochs)
        self.n_images = None if n_images is None else int(n_images)
        self.batch_size = int(batch_size)
        self.cache_dir = cache_dir
        self.extractor = extractor
        self.kid_subsets = int(kid_subsets)
        self.kid_subset_size = None if kid_subset_size is None else int(kid_subset_size)
        self.progress = bool(progress)
        self.spp = None if spp is None else check_spp(spp, "callbacks.fid.spp")
        if screen_images is not None and int(screen_images) < 4:
            raise ConfigError(
                f"callbacks.fid.screen_images={screen_images}: expected >= 4 (KID on halves of the screen) "
                "or null (no screen: every evaluation a full FID)"
            )
        if not (isinstance(screen_margin, (int, float)) and 0 <= screen_margin < math.inf):
            raise ConfigError(
                f"callbacks.fid.screen_margin={screen_margin!r}: expected a number >= 0 (0.2: epochs whose "
                "screen KID is within 20 % of the lowest go on to the full FID)"
            )
        self.screen_images = None if screen_images is None else int(screen_images)
        self.screen_margin = float(screen_margin)
        if (
            isinstance(fid_resamples, bool)
            or not isinstance(fid_resamples, int)
            or fid_resamples == 1
            or fid_resamples < 0
        ):
            raise ConfigError(
                f"callbacks.fid.fid_resamples={fid_resamples!r}: expected an integer >= 2 (bootstrap resamples for "
                "the FID's std, val/fid_std) or 0 (none)"
            )
        self.fid_resamples = int(fid_resamples)
        self.history: list[dict] = []  # per evaluated epoch: epoch, fid, fid_std, kid, kid_std, brightness, ...
        self._real: FeatureStats | None = None
        self._real_mean: float | None = None
        self._real_sums: np.ndarray | None = None

    @property
    def state_key(self) -> str:
        return type(self).__name__  # one FID callback per trainer; its state survives changed arguments

    def _extractor(self):
        if self.extractor is None:
            self.extractor = InceptionFeatures(batch_size=self.batch_size, progress=self.progress)
        return self.extractor

    def real_stats(self, trainer: Trainer) -> FeatureStats:
        if self._real is None:
            patches = real_patches(trainer)
            cache = Path(self.cache_dir) if self.cache_dir else run_dir(trainer) / "fid_cache"
            key = dataset_key(patches)
            if not isinstance(self._extractor(), InceptionFeatures):
                key += f"_{type(self.extractor).__name__}"  # other features never mix with Inception's
            self._real = cached_reference_stats(patches, cache, key, extractor=self._extractor())
        return self._real

    def real_mean(self, trainer: Trainer) -> float:
        """Mean grey of the real training patches (the reference of ``val/brightness``)."""
        if self._real_mean is None:
            self._real_mean = float(real_patches(trainer).mean(dtype=np.float64))
        return self._real_mean

    def real_level_sums(self, trainer: Trainer) -> np.ndarray:
        """``level_sums`` (len, 4) of each real training patch, segmented as they were mined (computed once)."""
        if self._real_sums is None:
            patches = real_patches(trainer)
            self._real_sums = level_sums(patches, classical_masks(trainer, patches))
        return self._real_sums

    def real_levels(self, trainer: Trainer) -> tuple[float, float]:
        """(particle, background) mean grey of the real training patches, segmented as they were mined."""
        return levels(self.real_level_sums(trainer))

    def brightness_tolerance(self, trainer: Trainer) -> dict[str, list[float]]:
        """The particle and background brightness ranges the real patches span (`brightness_tolerance`)."""
        polarity = getattr(getattr(trainer, "datamodule", None), "polarity", None) or "bright"
        return brightness_tolerance(self.real_level_sums(trainer), polarity)

    def check_ready(self) -> None:
        """Everything this callback can check before data are mined: the feature network (its file and hash
        for Inception) loads, and a fixed KID subset fits the fixed number of images. Called by drgan.train."""
        if self.kid_subset_size is not None and self.n_images is not None and self.kid_subset_size > self.n_images:
            raise ConfigError(
                f"callbacks.fid.kid_subset_size={self.kid_subset_size} exceeds callbacks.fid.n_images="
                f"{self.n_images}: a subset is drawn from the images without replacement"
            )
        network = getattr(self._extractor(), "network", None)  # loads (and checks) the Inception file now, seconds
        del network

    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        """After mining, before the first step: a fixed KID subset must fit the real patches."""
        if self.kid_subset_size is None or getattr(getattr(trainer, "datamodule", None), "real_patches", None) is None:
            return
        n_real = len(real_patches(trainer))
        n = min(self.n_images or n_real, n_real)
        if self.kid_subset_size is not None and self.kid_subset_size > n:
            raise ConfigError(
                f"callbacks.fid.kid_subset_size={self.kid_subset_size} exceeds the {n} images of each "
                "KID sample (real training patches / callbacks.fid.n_images); lower it or leave it null "
                "(half the sample)"
            )

    def latest(self, epoch: int) -> dict | None:
        return next((h for h in reversed(self.history) if h["epoch"] == epoch), None)

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        epoch = trainer.current_epoch
        if trainer.sanity_checking or (epoch + 1) % self.every_n_epochs:
            return
        if trainer.fast_dev_run:  # a smoke test of the step, like Lightning's own checkpoint callbacks skip
            log.info("fast_dev_run: FID skipped")
            return
        start = time.perf_counter()
        real = self.real_stats(trainer)
        n = self.n_images or real.n
        seed_base = FID_SEED_BASE + 100_003 * epoch
        progress = self.progress and trainer.is_global_zero
        screen = self.screen_images if self.screen_images is not None and self.screen_images < n else None
        # Under DDP each rank renders and embeds its share; the features are gathered, so every rank scores
        # the same n images (the same ones as a single process would: seeds follow the image index).
        feats, sums, grey = self._render_part(trainer, pl_module, 0, screen or n, seed_base, progress)
        screen_kid = None
        if screen is not None:
            screen_kid = kid(feats, real.features, self.kid_subsets, None, seed=epoch)[0]
            lowest = min((h["screen_kid"] for h in self.history if h.get("screen_kid") is not None), default=math.inf)
            if screen_kid > lowest + abs(lowest) * self.screen_margin:
                self._record(trainer, pl_module, epoch, start, (math.nan,) * 4, grey, sums, screen, screen_kid)
                return
            more = self._render_part(trainer, pl_module, screen, n, seed_base, progress)
            feats, sums, grey = (np.concatenate([a, b]) for a, b in zip((feats, sums, grey), more))
        fid = FeatureStats.from_features(feats).fid(real)
        fid_std = fid_bootstrap_std(feats, real, self.fid_resamples, seed=epoch) if self.fid_resamples else math.nan
        kid_mean, kid_std = kid(feats, real.features, self.kid_subsets, self.kid_subset_size, seed=epoch)
        self._record(trainer, pl_module, epoch, start, (fid, fid_std, kid_mean, kid_std), grey, sums, n, screen_kid)

    def _render_part(
        self, trainer: Trainer, pl_module: LightningModule, first: int, stop: int, seed_base: int, progress: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Images first .. stop-1 of an evaluation (this rank's share, gathered): their features, level sums
        (`level_sums` of the exact labels, then of `classical_masks`), greys."""
        count = stop - first
        mine = [first + i for i in rank_share(count, trainer.global_rank, trainer.world_size)]
        fake, fake_masks = render_samples(
            pl_module, stop, seed_base, progress=progress, spp=self.spp, indices=mine, masks=True
        )
        feats = gather_rows(trainer, np.asarray(self._extractor().features(fake), dtype=np.float64), count)
        sums = np.concatenate([level_sums(fake, fake_masks), level_sums(fake, classical_masks(trainer, fake))], axis=1)
        sums = gather_rows(trainer, sums, count)  # (count, 8): exact labels, then the classical segmentation
        grey = gather_rows(trainer, fake.mean(axis=(1, 2), dtype=np.float64), count)  # every image has as many pixels
        return feats, sums, grey

    def _record(
        self,
        trainer: Trainer,
        pl_module: LightningModule,
        epoch: int,
        start: float,
        scores: tuple[float, float, float, float],
        grey: np.ndarray,
        sums: np.ndarray,
        n: int,
        screen_kid: float | None,
    ) -> None:
        """History entry, log line and logged metrics of one evaluation; scores: FID, its bootstrap std, KID, its
        std (FID NaN: screened out)."""
        fid, fid_std, kid_mean, kid_std = scores
        brightness = float(grey.mean()) / max(self.real_mean(trainer), 1e-6)
        polarity = getattr(trainer.datamodule, "polarity", None) or "bright"
        tones = self._tones(trainer, sums, polarity)
        seconds = time.perf_counter() - start
        entry = {
            "epoch": epoch,
            "step": training_steps(trainer),
            "fid": fid,
            "fid_std": fid_std,
            "kid": kid_mean,
            "kid_std": kid_std,
            "brightness": brightness,
            **tones,
            "n_images": n,
            "seconds": seconds,
        }
        if screen_kid is not None:
            entry["screen_kid"] = float(screen_kid)
        self.history = [h for h in self.history if h["epoch"] != epoch] + [entry]
        if trainer.is_global_zero:
            self._log_line(entry, polarity)
        metrics = [
            ("val/fid", fid),
            ("val/fid_std", fid_std),
            ("val/kid", kid_mean),
            ("val/brightness", brightness),
            *((f"val/{k}", v) for k, v in tones.items()),
            ("time/fid_s", seconds),
        ]
        if screen_kid is not None:
            metrics.append(("val/screen_kid", screen_kid))
        for key, value in metrics:
            pl_module.log(key, float(value), on_step=False, on_epoch=True, prog_bar=key == "val/fid", sync_dist=True)

    def _tones(self, trainer: Trainer, sums: np.ndarray, polarity: str) -> dict[str, float]:
        """Particle and background grey against the real patches' (as the classical segmentation sees both sides;
        the exact labels where it found no particle) and the render's contrast (exact labels)."""
        particle, background = levels(sums[:, :4])
        seen_particle, seen_background = levels(sums[:, 4:])
        if not math.isfinite(seen_particle):  # the threshold found no particle in any image (tiny renders)
            seen_particle, seen_background = particle, background
        real_particle, real_background = self.real_levels(trainer)
        return {
            "particle_brightness": level_ratio(seen_particle, real_particle, polarity),
            "background_brightness": level_ratio(seen_background, real_background, polarity),
            "contrast": contrast(particle, background, polarity),
        }

    def _log_line(self, entry: dict, polarity: str) -> None:
        """An evaluation's log line: its scores, or that the KID screen left it out."""
        if math.isfinite(entry["fid"]):
            log.info(
                "epoch %d: FID %.4g (bootstrap std %.2g), KID %.4g, brightness %.2f x real (particles %.2f x, "
                "background %.2f x, contrast %.2f for %s particles; %d images, %.1f s)",
                *(entry[k] for k in ("epoch", "fid", "fid_std", "kid", "brightness", "particle_brightness")),
                entry["background_brightness"], entry["contrast"], polarity, entry["n_images"], entry["seconds"],
            )  # fmt: skip
        else:
            log.info(
                "epoch %d: screened out (KID of %d images %.4g, above the lowest so far by more than %g %%): "
                "no full FID (%.1f s)",
                entry["epoch"], entry["n_images"], entry["screen_kid"], 100 * self.screen_margin, entry["seconds"],
            )  # fmt: skip

    def state_dict(self) -> dict:
        return {"history": [dict(h) for h in self.history]}

    def load_state_dict(self, state_dict: dict) -> None:
        self.history = [dict(h) for h in state_dict.get("history", [])]
