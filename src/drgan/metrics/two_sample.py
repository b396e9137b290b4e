"""A classifier two-sample test: can a small CNN tell two sets of grey patches apart?

Lopez-Paz and Oquab (ICLR 2017, "Revisiting classifier two-sample tests"): train a classifier to separate
sample A (label 0) from sample B (label 1) and score it on patches it was not trained on. If A and B come from
one distribution, no classifier beats chance: the held-out accuracy is near 0.5. Unlike FID at ~130 images
(biased, with a spread of several points between draws), the accuracy has a known null distribution,
Binomial(total, 0.5), so it comes with an interval and a p-value.

Here:
- balanced: n = min(len(A), len(B)) patches of each, the larger sample drawn at random (seeded);
- k-fold cross-validation: every patch is predicted exactly once, by a network that never trained on it; the
  folds keep a *group* (e.g. all the patches of one real image) together, so that a network cannot score by
  recognising an image whose other patches it trained on;
- the network (``PatchClassifier``): three 3x3 conv blocks with max pooling, global average pooling and a linear
  logit, on patches area-downsampled to ``input_size`` px; random flips / 90-degree rotations in training and
  the mean logit over the 8 symmetries in testing;
- accuracy = correct / total over the held-out predictions (B when the logit exceeds a threshold fitted on the
  fold's training part), with a 95 % Clopper-Pearson
  (exact binomial) interval, the Wilson interval, and the one-sided binomial p-value P(X >= correct | p = 0.5);
  the AUC of the held-out scores (Mann-Whitney, ties counted half).

The binomial interval treats the 2n predictions as independent trials; the k networks share training data, so
this is the usual approximation of the classifier two-sample test, slightly optimistic.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from drgan.core.errors import ConfigError, DataError

CONFIDENCE = 0.95


# --- statistics of the held-out predictions -----------------------------------------------------------------


def _check_counts(k: int, n: int) -> None:
    if isinstance(k, bool) or isinstance(n, bool) or int(k) != k or int(n) != n or not 0 <= k <= n or n < 1:
        raise ConfigError(f"binomial counts k={k}, n={n}: expected integers with 0 <= k <= n and n >= 1")


def _check_confidence(confidence: float) -> None:
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence={confidence}: expected a level in (0, 1), e.g. 0.95")


def exact_interval(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Clopper-Pearson interval of a binomial proportion k / n: the quantiles of Beta(k, n - k + 1) and
    Beta(k + 1, n - k) at (1 - confidence) / 2 on each side; 0 and 1 at the ends (k = 0, k = n)."""
    from scipy.stats import beta

    _check_counts(k, n)
    _check_confidence(confidence)
    alpha = 1.0 - confidence
    low = 0.0 if k == 0 else float(beta.ppf(alpha / 2, k, n - k + 1))
    high = 1.0 if k == n else float(beta.ppf(1 - alpha / 2, k + 1, n - k))
    return low, high


def wilson_interval(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval: (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n), p = k / n."""
    from scipy.stats import norm

    _check_counts(k, n)
    _check_confidence(confidence)
    z = float(norm.ppf(0.5 + confidence / 2))
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def p_above_chance(k: int, n: int) -> float:
    """One-sided binomial p-value of k correct out of n against chance: P(X >= k), X ~ Binomial(n, 0.5)."""
    from scipy.stats import binom

    _check_counts(k, n)
    return float(binom.sf(k - 1, n, 0.5))


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve of ``scores`` (higher = label 1): the Mann-Whitney U / (n0 n1), ties half."""
    from scipy.stats import rankdata

    scores, labels = np.asarray(scores, dtype=np.float64).ravel(), np.asarray(labels).ravel()
    if scores.shape != labels.shape:
        raise ConfigError(f"auc: {scores.size} scores but {labels.size} labels")
    if not set(np.unique(labels).tolist()) <= {0, 1}:
        raise ConfigError("auc: labels must be 0 or 1")
    n1 = int((labels == 1).sum())
    n0 = labels.size - n1
    if n0 == 0 or n1 == 0:
        raise ConfigError(f"auc: needs both labels (got {n0} of label 0, {n1} of label 1)")
    if not np.isfinite(scores).all():
        raise ConfigError("auc: scores must be finite")
    ranks = rankdata(scores)  # average ranks for ties
    u = ranks[labels == 1].sum() - n1 * (n1 + 1) / 2
    return float(u / (n0 * n1))


# --- folds ----------------------------------------------------------------------------------------------------


def group_folds(labels: np.ndarray, groups: Sequence, k: int, seed: int) -> np.ndarray:
    """Fold index (0 .. k-1) of every sample: each group entirely in one fold, and each label's samples spread
    as evenly as the groups allow (each label's groups, largest first in a seeded random order among equals,
    go to the fold that has fewest samples of that label)."""
    labels = np.asarray(labels)
    groups = np.asarray([str(g) for g in groups])
    if len(groups) != len(labels):
        raise ConfigError(f"group_folds: {len(labels)} labels but {len(groups)} groups")
    rng = np.random.default_rng(seed)
    fold = np.full(len(labels), -1, dtype=np.int64)
    for label in np.unique(labels):
        mine = labels == label
        names, sizes = np.unique(groups[mine], return_counts=True)
        mixed = set(names) & set(groups[~mine])
        if mixed:
            raise ConfigError(
                f"group_folds: group(s) {sorted(mixed)[:3]} hold both labels (a group must belong to one sample)"
            )
        order = rng.permutation(len(names))
        order = order[np.argsort(-sizes[order], kind="stable")]
        filled = np.zeros(k, dtype=np.int64)
        for g in order:
            target = int(np.argmin(filled))  # the first of the emptiest folds
            fold[mine & (groups == names[g])] = target
            filled[target] += sizes[g]
    return fold


# --- the classifier -------------------------------------------------------------------------------------------


class PatchClassifier(nn.Module):
    """(B, 1, S, S) grey patches in [0, 1] -> (B,) logits. Three conv-ReLU-maxpool blocks (width, 2 width,
    4 width channels), global average pooling, a linear logit. No normalisation layers: batch statistics of a
    few hundred patches make the held-out threshold drift, and per-sample normalisation would hide the grey
    level, which is part of what tells two sources apart."""

    def __init__(self, width: int = 16):
        super().__init__()
        layers, channels = [], 1
        for out in (width, 2 * width, 4 * width):
            layers += [nn.Conv2d(channels, out, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
            channels = out
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.features(x - 0.5)  # grey in [0, 1]: centred; the absolute level stays visible
        return self.head(x.mean(dim=(2, 3))).squeeze(1)


def dihedral(x: torch.Tensor, k: int) -> torch.Tensor:
    """Symmetry k (0..7) of the square patches x (..., S, S): k % 4 quarter turns, transposed when k >= 4."""
    x = torch.rot90(x, k % 4, dims=(-2, -1))
    return x.transpose(-2, -1) if k >= 4 else x


def downsample(patches: np.ndarray, size: int) -> torch.Tensor:
    """(N, H, W) patches -> (N, 1, size, size) float32 by area averaging (antialiased bilinear when H is not a
    multiple of size)."""
    x = torch.from_numpy(np.ascontiguousarray(patches, dtype=np.float32)).unsqueeze(1)
    if x.shape[-1] == size:
        return x
    if x.shape[-1] % size == 0:
        return F.avg_pool2d(x, x.shape[-1] // size)
    return F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)


@dataclass(frozen=True)
class ClassifierSettings:
    folds: int = 5
    epochs: int = 30
    input_size: int = 64  # px: patches are area-downsampled to this before the network
    batch_size: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-4
    width: int = 16  # channels of the first conv block
    seed: int = 0

    def check(self) -> None:
        for key in ("folds", "epochs", "input_size", "batch_size", "width"):
            value = getattr(self, key)
            low = {"folds": 2, "input_size": 8}.get(key, 1)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"test.{key}={value!r}: expected an integer >= {low}")
        if not self.lr > 0 or not self.weight_decay >= 0:
            raise ConfigError(f"test.lr={self.lr}, test.weight_decay={self.weight_decay}: expected lr > 0, decay >= 0")


def _train_one(x: torch.Tensor, y: torch.Tensor, settings: ClassifierSettings, seed: int, step) -> PatchClassifier:
    torch.manual_seed(seed)
    net = PatchClassifier(settings.width)
    optimiser = torch.optim.AdamW(net.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    rng = torch.Generator().manual_seed(seed)
    net.train()
    for _ in range(settings.epochs):
        order = torch.randperm(len(x), generator=rng)
        for start in range(0, len(x), settings.batch_size):
            batch = order[start : start + settings.batch_size]
            k = int(torch.randint(8, (), generator=rng))
            loss = F.binary_cross_entropy_with_logits(net(dihedral(x[batch], k)), y[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
        step()
    return net.eval()


@torch.no_grad()
def _logits(net: PatchClassifier, x: torch.Tensor) -> np.ndarray:
    return torch.stack([net(dihedral(x, k)) for k in range(8)]).mean(0).numpy()


def _check_sample(name: str, patches: np.ndarray) -> np.ndarray:
    patches = np.asarray(patches)
    if patches.ndim != 3 or patches.shape[1] != patches.shape[2]:
        raise DataError(f"two-sample test: sample {name} has shape {patches.shape} (expected (N, S, S) square patches)")
    if not np.issubdtype(patches.dtype, np.floating) or not np.isfinite(patches).all():
        raise DataError(f"two-sample test: sample {name} must hold finite float grey values in [0, 1]")
    return patches


def two_sample_test(
    a: np.ndarray,
    b: np.ndarray,
    settings: ClassifierSettings = ClassifierSettings(),
    groups_a: Sequence | None = None,
    groups_b: Sequence | None = None,
    progress: bool = True,
) -> dict:
    """Classifier two-sample test of patch sets ``a`` (label 0) and ``b`` (label 1), each (N, S, S) in [0, 1].

    groups_*: one name per patch (e.g. its image id): a group's patches share a fold; None: each patch its own.
    Returns a JSON-ready dict: n_per_class, total, correct, accuracy, interval (exact), wilson, p_value, auc,
    per-fold accuracies, the settings and wall time."""
    settings.check()
    a, b = _check_sample("A", a), _check_sample("B", b)
    if a.shape[1:] != b.shape[1:]:
        raise DataError(f"two-sample test: patches of A are {a.shape[1]} px, of B {b.shape[1]} px (expected one size)")
    if a.shape[1] < settings.input_size:
        raise ConfigError(f"test.input_size={settings.input_size} exceeds the patches' {a.shape[1]} px")
    groups_a = [f"a{i}" for i in range(len(a))] if groups_a is None else [str(g) for g in groups_a]
    groups_b = [f"b{i}" for i in range(len(b))] if groups_b is None else [str(g) for g in groups_b]
    if len(groups_a) != len(a) or len(groups_b) != len(b):
        raise ConfigError(
            f"two-sample test: {len(groups_a)} / {len(groups_b)} group names for "
            f"{len(a)} / {len(b)} patches (expected one per patch)"
        )
    x, y, fold, n_groups = _balanced_folds(a, b, groups_a, groups_b, settings)
    start = time.perf_counter()
    scores = _held_out_scores(x, y, fold, settings, progress)
    n = len(y) // 2
    predicted = (scores > 0).astype(np.float32)
    correct = int((predicted == y).sum())
    total = 2 * n
    per_fold = [
        {
            "fold": f,
            "test_patches": int((fold == f).sum()),
            "accuracy": round(float((predicted[fold == f] == y[fold == f]).mean()), 4),
        }
        for f in range(settings.folds)
    ]
    return {
        "n_per_class": n,
        "available": {"A": len(a), "B": len(b)},
        "groups": n_groups,
        "total": total,
        "correct": correct,
        "accuracy": round(correct / total, 4),
        "interval": [round(v, 4) for v in exact_interval(correct, total)],
        "interval_method": f"Clopper-Pearson (exact binomial), {CONFIDENCE:.0%}",
        "wilson": [round(v, 4) for v in wilson_interval(correct, total)],
        "p_value": float(f"{p_above_chance(correct, total):.4g}"),
        "p_value_method": "one-sided binomial, P(X >= correct), X ~ Binomial(total, 0.5)",
        "auc": round(auc(scores, y), 4),
        "folds": per_fold,
        "settings": asdict(settings),
        "wall_s": round(time.perf_counter() - start, 1),
    }


def _balanced_folds(a, b, groups_a, groups_b, settings: ClassifierSettings):
    """(inputs, labels, fold of each, number of groups): as many patches of each sample (the smaller's count, drawn
    with the settings' seed), downsampled to the classifier's input, in folds that keep a group together and hold
    both samples each; a DataError where they cannot."""
    n = min(len(a), len(b))
    needed = 2 * settings.folds
    if n < needed:
        raise DataError(
            f"two-sample test: {len(a)} patches in A and {len(b)} in B; {settings.folds} folds need at "
            f"least {needed} of each (2 per fold); add patches or lower test.folds"
        )
    rng = np.random.default_rng(settings.seed)
    pick_a = np.sort(rng.choice(len(a), n, replace=False))
    pick_b = np.sort(rng.choice(len(b), n, replace=False))
    x = torch.cat([downsample(a[pick_a], settings.input_size), downsample(b[pick_b], settings.input_size)])
    y = np.r_[np.zeros(n), np.ones(n)].astype(np.float32)
    groups = [f"A:{groups_a[i]}" for i in pick_a] + [f"B:{groups_b[i]}" for i in pick_b]
    fold = group_folds(y, groups, settings.folds, settings.seed)
    n_groups = len(set(groups))
    if len(np.unique(fold)) < settings.folds or any(len(np.unique(y[fold == f])) < 2 for f in range(settings.folds)):
        raise DataError(
            f"two-sample test: {n_groups} groups (e.g. images) cannot fill {settings.folds} folds with "
            "both samples; lower test.folds or add images"
        )
    return x, y, fold, n_groups


def _held_out_scores(x, y, fold, settings: ClassifierSettings, progress: bool) -> np.ndarray:
    """Each patch's held-out score: the logit of the classifier trained on the other folds minus that fold's
    threshold (> 0 predicts B)."""
    from tqdm.auto import tqdm

    scores = np.full(len(y), np.nan)
    bar = tqdm(
        total=settings.folds * settings.epochs,
        desc="two-sample folds x epochs",
        unit="epoch",
        disable=not progress,
        leave=False,
    )
    try:
        for f in range(settings.folds):
            train, test = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
            net = _train_one(
                x[train], torch.from_numpy(y[train]), settings, settings.seed * 1000 + f, lambda: bar.update(1)
            )
            # The decision threshold from the training part only: midway between its two classes' median logits
            # (a network trained briefly has not yet centred its bias at 0).
            fitted = _logits(net, x[train])
            threshold = 0.5 * (np.median(fitted[y[train] == 0]) + np.median(fitted[y[train] == 1]))
            scores[test] = _logits(net, x[test]) - threshold
    finally:
        bar.close()
    return scores
