"""What a cheaper FID evaluation would have chosen: a finished GAN run's epochs re-scored with fewer FID images or
at a lower spp, beside the evaluation the run made (issue 68: on tio2_sem the FID passes are half the GAN's time).

    python experiments/pipeline/fid_cost.py RUN/train [--n 64 96 128] [--spp 0 64]

Each epoch checkpoint (checkpoints/epochs/epoch_XXX.ckpt) renders the evaluation's own images (constellation i of its
phi bank, seed FID_SEED_BASE + 100003 x epoch + i, as drgan.callbacks.fid renders them) at each --spp (0: the
training spp), and the FID of the first n of them against the run's cached real statistics is printed for each
--n, with its bootstrap std; n = 128 at the training spp is the run's own evaluation (the check that the renders are
the same). The last lines say which epoch the lowest FID of each setting picks (the best-epoch rule also weighs the
std and the parameters' spread; the lowest FID is its first cut).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from drgan.callbacks.fid import FID_SEED_BASE, render_samples
from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats, fid_bootstrap_std
from drgan.metrics.inception import InceptionFeatures
from drgan.models.gan_module import GANModule


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a drgan.train run folder (checkpoints/epochs/, fid_cache/, patches/)")
    parser.add_argument("--n", type=int, nargs="+", default=[64, 96, 128], help="FID images (prefixes of the largest)")
    parser.add_argument("--spp", type=int, nargs="+", default=[0, 64], help="render spp; 0: the training spp")
    parser.add_argument("--epochs", type=int, nargs="+", default=None, help="these epochs only (default: every one)")
    args = parser.parse_args()
    caches = sorted((args.run / "fid_cache").glob("real_*.npz"))
    if len(caches) != 1:
        raise SystemExit(f"{args.run}/fid_cache: expected one real statistics file, found {len(caches)}")
    real = FeatureStats.load(caches[0])
    table = json.loads((args.run / "checkpoints" / "best_epoch.json").read_text()).get("table", [])
    logged = {int(r["epoch"]): r for r in table}
    patches = PatchSet.load(args.run / "patches")
    extractor = InceptionFeatures(batch_size=16)
    n_max = max(args.n)
    rows: dict[tuple[int, int], dict[int, tuple[float, float]]] = {}
    print(f"command: python experiments/pipeline/fid_cost.py {args.run} --n {' '.join(map(str, args.n))} "
          f"--spp {' '.join(map(str, args.spp))}" + (f" --epochs {' '.join(map(str, args.epochs))}" if args.epochs else ""))  # fmt: skip
    print(
        "\n| epoch | spp | render s per image | " + " | ".join(f"FID n={n} (std)" for n in args.n) + " | logged FID |"
    )
    print("|---|---|---|" + "---|" * (len(args.n) + 1))
    for ckpt in sorted((args.run / "checkpoints" / "epochs").glob("epoch_*.ckpt")):
        epoch = int(ckpt.stem.split("_")[1])
        if args.epochs is not None and epoch not in args.epochs:
            continue
        module = GANModule.load_from_checkpoint(ckpt, map_location="cpu")
        module.eval()
        if module.textured:
            module.use_background_texture(patches.background)
        for spp in args.spp:
            start = time.perf_counter()
            images = render_samples(module, n_max, FID_SEED_BASE + 100_003 * epoch, spp=spp or None)
            per_image = (time.perf_counter() - start) / n_max
            feats = np.asarray(extractor.features(images), dtype=np.float64)
            scores = {}
            for n in args.n:
                fid = FeatureStats.from_features(feats[:n]).fid(real)
                scores[n] = (fid, fid_bootstrap_std(feats[:n], real, 10, seed=epoch))
            rows[(epoch, spp)] = scores
            own = logged.get(epoch, {}).get("fid")
            cells = " | ".join(f"{f:.1f} ({s:.1f})" for f, s in scores.values())
            print(f"| {epoch} | {spp or 'training'} | {per_image:.2f} | {cells} | "
                  f"{'' if own is None else f'{own:.1f}'} |", flush=True)  # fmt: skip
    print()
    for spp in args.spp:
        for n in args.n:
            fids = {e: s[n][0] for (e, sp), s in rows.items() if sp == spp}
            order = sorted(fids, key=fids.get)
            print(f"spp {spp or 'training'}, n={n}: lowest FID at epoch {order[0]} (epochs by FID: {order})")


if __name__ == "__main__":
    main()
