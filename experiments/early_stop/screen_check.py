"""Does the FID callback's KID screen keep the epochs that the full FID would choose? Checked on a recorded run.

    python experiments/early_stop/screen_check.py RUN_FOLDER [--screen 48] [--margin 0.2] [--draws 3]

For every epoch checkpoint the run kept (<run>/checkpoints/epochs/epoch_XXX.ckpt), the FID images are rendered
exactly as drgan.callbacks.fid renders them in training (the epoch's seeds, the module's phi bank, the training
spp, the run's background texture), and scored against the run's cached real statistics (<run>/fid_cache): the full FID and KID over all
images, and the screen's KID over the first --screen images (what the callback computes), plus the KID of
--draws - 1 further disjoint blocks of --screen images to show how much a screen of that size moves. Then the
callback's rule (an epoch goes on to the full FID when its screen KID is at most (1 + margin) x the lowest
screen KID so far) is replayed in epoch order: which epochs would have been screened out, and whether the epoch
of lowest full FID survives. Prints a markdown table. Heavy: renders every image of every epoch once.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from drgan.callbacks.fid import FID_SEED_BASE, render_samples
from drgan.metrics.feature_distances import FeatureStats, kid
from drgan.metrics.inception import InceptionFeatures


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--screen", type=int, default=48)
    parser.add_argument("--margin", type=float, default=0.2)
    parser.add_argument("--draws", type=int, default=3)
    args = parser.parse_args(argv)

    from drgan.models.gan_module import GANModule

    caches = sorted((args.run / "fid_cache").glob("real_*_clean_*.npz"))
    if len(caches) != 1:
        sys.exit(
            f"{args.run}/fid_cache: expected one cached real-statistics file (real_*_clean_HxW.npz), found "
            f"{[c.name for c in caches]}"
        )
    real = FeatureStats.load(caches[0])
    extractor = InceptionFeatures(batch_size=16, progress=False)
    rows = []
    for ckpt in sorted((args.run / "checkpoints" / "epochs").glob("epoch_*.ckpt")):
        epoch = int(ckpt.stem.split("_")[1])
        module = GANModule.load_from_checkpoint(ckpt, weights_only=True)
        if module.textured:  # the real film texture of the run's background patches, as in training
            from drgan.data.patches import PatchSet

            module.use_background_texture(PatchSet.load(args.run / "patches").background)
        n = real.n
        start = time.perf_counter()
        images = render_samples(module, n, FID_SEED_BASE + 100_003 * epoch, progress=True)
        feats = np.asarray(extractor.features(images), dtype=np.float64)
        blocks = [
            kid(feats[i * args.screen : (i + 1) * args.screen], real.features, 100, None, seed=epoch)[0]
            for i in range(min(args.draws, n // args.screen))
        ]
        rows.append(
            {
                "epoch": epoch,
                "fid": FeatureStats.from_features(feats).fid(real),
                "kid": kid(feats, real.features, 100, None, seed=epoch)[0],
                "screen_kid": blocks[0],
                "blocks": blocks,
                "seconds": time.perf_counter() - start,
            }
        )
        print(f"epoch {epoch}: FID {rows[-1]['fid']:.1f}, screen KIDs {np.round(blocks, 4)}", file=sys.stderr)

    lowest, kept = math.inf, []
    for row in rows:  # the callback's rule, in epoch order
        row["full"] = row["screen_kid"] <= lowest + abs(lowest) * args.margin
        lowest = min(lowest, row["screen_kid"])
        kept.append(row["full"])
    best = min(rows, key=lambda r: r["fid"])
    print(
        f"| epoch | full FID | full KID | screen KID (first {args.screen}) | KID of other blocks of {args.screen} "
        f"| full FID computed (margin {args.margin:g}) |"
    )
    print("|---|---|---|---|---|---|")
    for row in rows:
        others = ", ".join(f"{b:.4f}" for b in row["blocks"][1:])
        print(
            f"| {row['epoch']} | {row['fid']:.1f} | {row['kid']:.4f} | {row['screen_kid']:.4f} | {others} | "
            f"{'yes' if row['full'] else 'no (screened out)'} |"
        )
    print(
        f"\nlowest full FID: epoch {best['epoch']} ({best['fid']:.1f}); "
        f"{'kept' if best['full'] else 'SCREENED OUT'} by the screen; "
        f"{sum(kept)} of {len(rows)} evaluations went on to the full FID."
    )


if __name__ == "__main__":
    main()
