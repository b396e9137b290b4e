"""Real-vs-real FID: the floor against which a GAN's training FID on a data set is read.

    python experiments/tio2_tsem/real_fid.py DATASET_DIR [--splits 5] [--seed 0] [--cache DIR]

DATASET_DIR holds images/, split.json (train / test ids) and masks/ (unused here). The train patches are
mined exactly as training mines them (drgan.data.datamodule.RealPatchDataModule: crop_rows auto, 256 px,
stride 288, >= 3 whole particles, polarity auto), and the FID is computed as the FID callback computes it
(drgan.callbacks.fid: TF-Inception pool3 features, FeatureStats.from_features(a).fid(b)). Printed, as a
markdown table:

- train half vs train half, over random splits: by image id (one image's patches stay in one half; the
  halves are balanced by patch count) and plain random (patches of one image may land in both halves);
- train quarter vs train quarter (by image id), and a 1/n extrapolation from the quarter and half values
  to two sets of n_train patches each (what training compares) and to infinitely many;
- test vs train: the TEST images mined the same way (read_grey(path, "auto"), mine_patches with the polarity
  found on the train images), for this measurement only: nothing is trained or tuned on them. FID(test,
  all train), and like-for-like at the test set's size: n_test random train patches vs all train patches
  (a subset of the reference: biased low), and n_test patches of held-out train images vs the remaining
  train patches, beside FID(test, the same remaining train patches).

FID is biased upward for small samples (by roughly a constant / n): compare only numbers of equal n. KID
(unbiased, drgan.metrics.feature_distances.kid) is printed beside each FID. Mined patches and features are cached under
--cache (default /tmp/real_fid/<dataset name>), never in the repository: they show the licensed images.
"""

from __future__ import annotations

import argparse
import json
import logging
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from drgan.core.errors import ConfigError, DataError
from drgan.core.io import write_with
from drgan.data.datamodule import RealPatchDataModule
from drgan.data.images import list_images, read_grey, read_split
from drgan.data.patches import mine_patches
from drgan.metrics.feature_distances import FeatureStats, kid
from drgan.metrics.inception import InceptionFeatures

PATCH_SIZE = 256  # as renderer.resolution in training
STRIDE = 288  # conf/gan/experiment/tio2_sem.yaml and tio2_tsem.yaml
MIN_PARTICLES = 3  # conf/gan/data/real_patches.yaml
KID_SUBSETS = 100  # as the FID callback


def fid(a: np.ndarray, b: np.ndarray) -> float:
    """FID between two feature sets (N, 2048), as the FID callback: FeatureStats(a).fid(FeatureStats(b))."""
    return FeatureStats.from_features(a).fid(FeatureStats.from_features(b))


def kid_mean(a: np.ndarray, b: np.ndarray, seed: int) -> float:
    return kid(a, b, KID_SUBSETS, None, seed=seed)[0]


def balanced_image_split(ids: np.ndarray, parts: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Indices of ``parts`` groups of patches, whole images each: images in random order, each to the group
    with the fewest patches so far (ties: the first)."""
    groups: list[list[int]] = [[] for _ in range(parts)]
    for image in rng.permutation(np.unique(ids)):
        smallest = min(range(parts), key=lambda g: len(groups[g]))
        groups[smallest].extend(np.flatnonzero(ids == image).tolist())
    return [np.asarray(sorted(g), dtype=int) for g in groups]


def held_out_images(ids: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n patches of randomly drawn whole train images, every patch of the images not drawn): images are drawn
    until they hold >= n patches, then n of those patches are kept at random."""
    taken: list[int] = []
    order = rng.permutation(np.unique(ids))
    used = 0
    for image in order:
        if len(taken) >= n:
            break
        taken.extend(np.flatnonzero(ids == image).tolist())
        used += 1
    rest = np.flatnonzero(np.isin(ids, order[used:]))
    return np.sort(rng.choice(np.asarray(taken), n, replace=False)), rest


def cached(path: Path, compute: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Arrays from an .npz cache, computed and written atomically when absent."""
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    arrays = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_with(path, lambda handle: np.savez(handle, **arrays))
    return arrays


def mine_test(images_dir: Path, test_ids: list[str], polarity: str) -> dict[str, np.ndarray]:
    images = [read_grey(p, "auto") for p in list_images(images_dir, test_ids)]
    patches = mine_patches(
        images,
        test_ids,
        size=PATCH_SIZE,
        stride=STRIDE,
        min_particles=MIN_PARTICLES,
        n_background=0,
        polarity=polarity,
        progress=False,
    )
    return {
        "patches": patches.train,
        "ids": np.asarray(patches.train_ids),
        "shapes": np.asarray(sorted({im.shape for im in images})),
    }


def cropped_shapes(images_dir: Path, ids: list[str]) -> list[list[int]]:
    """The distinct (rows, cols) of the images after crop_rows auto."""
    return [list(s) for s in sorted({read_grey(p, "auto").shape for p in list_images(images_dir, ids)})]


def measure(dataset: Path, splits: int, seed: int, cache: Path, batch_size: int) -> tuple[dict, list[tuple]]:
    images_dir, split_path = dataset / "images", dataset / "split.json"
    if not images_dir.is_dir() or not split_path.is_file():
        raise DataError(f"dataset {dataset}: expected images/ and split.json inside")
    test_ids = list(read_split(split_path)["test"])
    module = RealPatchDataModule(
        dir=str(images_dir),
        split=str(split_path),
        crop_rows="auto",
        patch_size=PATCH_SIZE,
        stride=STRIDE,
        min_particles=MIN_PARTICLES,
        polarity="auto",
        cache_dir=str(cache / "patches_train"),
    )
    hits = [
        name
        for name in ("patches_train/source.json", "patches_test.npz", "features_train.npz", "features_test.npz")
        if (cache / name).is_file()
    ]
    start = time.perf_counter()
    module.setup("fit")
    train, train_ids = module.real_patches, np.asarray(module.patches.train_ids)
    polarity = module.polarity
    test = cached(cache / "patches_test.npz", lambda: mine_test(images_dir, test_ids, polarity))
    if set(test["ids"].tolist()) & set(train_ids.tolist()):
        raise DataError("a test image's patches are among the train patches: the split leaks")
    mined_s = time.perf_counter() - start
    extractor = InceptionFeatures(batch_size=batch_size, progress=True)
    start = time.perf_counter()
    f_train = cached(cache / "features_train.npz", lambda: {"f": extractor.features(train)})["f"]
    f_test = cached(cache / "features_test.npz", lambda: {"f": extractor.features(test["patches"])})["f"]
    features_s = time.perf_counter() - start
    if len(f_train) != len(train) or len(f_test) != len(test["patches"]):
        raise DataError(f"feature cache under {cache} belongs to other patches: delete it")
    n_train, n_test = len(f_train), len(f_test)
    rng = np.random.default_rng(seed)
    rows: dict[str, list[tuple]] = {}

    def add(name: str, n_a, n_b, fid_value: float, kid_value: float) -> None:
        rows.setdefault(name, []).append((n_a, n_b, fid_value, kid_value))

    for s in range(splits):
        a, b = balanced_image_split(train_ids, 2, rng)
        add(
            "train half vs train half, by image",
            len(a),
            len(b),
            fid(f_train[a], f_train[b]),
            kid_mean(f_train[a], f_train[b], s),
        )
        perm = rng.permutation(n_train)
        a, b = perm[: n_train // 2], perm[n_train // 2 :]
        add(
            "train half vs train half, plain random",
            len(a),
            len(b),
            fid(f_train[a], f_train[b]),
            kid_mean(f_train[a], f_train[b], s),
        )
        q = balanced_image_split(train_ids, 4, rng)
        add(
            "train quarter vs train quarter, by image",
            len(q[0]),
            len(q[1]),
            fid(f_train[q[0]], f_train[q[1]]),
            kid_mean(f_train[q[0]], f_train[q[1]], s),
        )
    add("test vs all train", n_test, n_train, fid(f_test, f_train), kid_mean(f_test, f_train, 0))
    for s in range(splits):
        sub = rng.choice(n_train, n_test, replace=False)
        add(
            "n_test random train patches vs all train (subset of the reference)",
            n_test,
            n_train,
            fid(f_train[sub], f_train),
            kid_mean(f_train[sub], f_train, s),
        )
        held, rest = held_out_images(train_ids, n_test, rng)
        add(
            "n_test patches of held-out train images vs the other train images",
            n_test,
            len(rest),
            fid(f_train[held], f_train[rest]),
            kid_mean(f_train[held], f_train[rest], s),
        )
        add(
            "test vs the same other train images",
            n_test,
            len(rest),
            fid(f_test, f_train[rest]),
            kid_mean(f_test, f_train[rest], s),
        )
    info = {
        "dataset": str(dataset),
        "polarity": polarity,
        "n_train": n_train,
        "n_test": n_test,
        "train_images": len(np.unique(train_ids)),
        "test_images_with_patches": len(np.unique(test["ids"])),
        "test_images": len(test_ids),
        "train_image_shapes": cropped_shapes(images_dir, module.train_ids),
        "test_image_shapes": test["shapes"].tolist(),
        "mined_s": round(mined_s, 1),
        "features_s": round(features_s, 1),
        "cache_hits": hits,
        "splits": splits,
        "seed": seed,
        "polarity_estimate": module.polarity_estimate,
    }
    return info, rows


def extrapolate(rows: dict[str, list[tuple]], n_train: int) -> tuple[float, float]:
    """FID = c + k (1/n_a + 1/n_b) through the by-image quarter and half means: (value at n_a = n_b = n_train,
    value at infinity)."""
    points = []
    for name in ("train quarter vs train quarter, by image", "train half vs train half, by image"):
        r = np.asarray(rows[name], dtype=float)
        points.append((np.mean(1 / r[:, 0] + 1 / r[:, 1]), r[:, 2].mean()))
    (x1, y1), (x2, y2) = points
    if x1 == x2:
        raise ConfigError("quarters and halves of equal size: cannot extrapolate")
    k = (y1 - y2) / (x1 - x2)
    c = y2 - k * x2
    return c + k * 2 / n_train, c


def table(info: dict, rows: dict[str, list[tuple]]) -> str:
    def pm(values) -> str:
        v = np.asarray(values, dtype=float)
        return f"{v.mean():.1f} +- {v.std(ddof=1):.1f}" if len(v) > 1 else f"{v[0]:.1f}"

    def n(values) -> str:
        lo, hi = min(values), max(values)
        return str(lo) if lo == hi else f"{lo}-{hi}"

    header = (
        f"{info['dataset']}: {info['n_train']} train patches from {info['train_images']} train images, "
        f"{info['n_test']} test patches from {info['test_images_with_patches']} of {info['test_images']} test "
        f"images; polarity {info['polarity']}; 256 px, stride 288, >= 3 particles; images after crop_rows auto "
        f"(rows, cols): train {info['train_image_shapes']}, test {info['test_image_shapes']}. "
        f"Mining {info['mined_s']} s, features {info['features_s']} s"
        f"{' (read from the cache: ' + ', '.join(info['cache_hits']) + ')' if info['cache_hits'] else ''}."
    )
    lines = [
        textwrap.fill(header, 120),
        "",
        "| comparison | runs | n (a) | n (b) | FID (mean +- std) | KID x 1000 (mean +- std) |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        a, b, f, k = zip(*r)
        lines.append(f"| {name} | {len(r)} | {n(a)} | {n(b)} | {pm(f)} | {pm(np.asarray(k) * 1000)} |")
    at_n, at_inf = extrapolate(rows, info["n_train"])
    lines += [
        "",
        textwrap.fill(
            "1/n extrapolation of the by-image quarter and half values "
            f"(FID = c + k (1/n_a + 1/n_b)): {at_n:.1f} at {info['n_train']} vs "
            f"{info['n_train']} (the training comparison's sizes), {at_inf:.1f} at infinite n.",
            120,
        ),
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="folder with images/, split.json")
    parser.add_argument("--splits", type=int, default=5, help="random splits / draws per comparison")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=None, help="default /tmp/real_fid/<dataset folder name>")
    parser.add_argument("--batch-size", type=int, default=16, help="Inception batch size")
    args = parser.parse_args()
    if args.splits < 2:
        raise ConfigError(f"--splits={args.splits}: expected >= 2 (a std needs two)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cache = args.cache or Path("/tmp/real_fid") / args.dataset.resolve().name
    info, rows = measure(args.dataset, args.splits, args.seed, cache, args.batch_size)
    print(table(info, rows))
    print("\n<!--\n" + json.dumps(info, indent=1) + "\n-->")


if __name__ == "__main__":
    main()
