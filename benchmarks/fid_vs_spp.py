"""FID of one trained generator rendered at several spp: how much of the FID is Monte Carlo noise.

    python benchmarks/fid_vs_spp.py runs/tio2_sem/tio2_sem_spp16/checkpoints/last.ckpt --spp 4 16 64

Renders the checkpoint's phi bank (as many images as real training patches) at each spp with the same
learned parameters and seeds, and scores them against the run's cached real statistics (clean-resized
Inception features of the real training patches).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from drgan.data.patches import PatchSet
from drgan.metrics.fid import FeatureStats, InceptionFeatures
from drgan.models.gan_module import GANModule


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path)
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    args = parser.parse_args()
    # The run folder holds patches/: checkpoints/last.ckpt or checkpoints/epochs/epoch_XXX.ckpt.
    run = next((p for p in args.ckpt.resolve().parents if (p / "patches").is_dir()), None)
    if run is None:
        sys.exit(f"{args.ckpt}: no run folder with patches/ above it (expected <run>/checkpoints/...ckpt)")
    real = PatchSet.load(run / "patches").train
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))
    module = GANModule.load_from_checkpoint(args.ckpt, map_location="cpu")
    module.eval()
    if module.textured:  # the stage texture of training, from the same run's background patches
        module.use_background_texture(PatchSet.load(run / "patches").background)
    print(f"command: python {' '.join(sys.argv)}\ncheckpoint epoch: see {args.ckpt.name}; {len(real)} real patches\n")
    print("| spp | FID | render s |")
    print("|---|---|---|")
    for spp in args.spp:
        start = time.perf_counter()
        bank = module.phi_bank
        images = np.stack([module.generator.sample(bank[i % len(bank)], seed=10_000 + i, spp=spp).image for i in range(len(real))])
        seconds = time.perf_counter() - start
        fid = FeatureStats.from_features(extractor.features(images)).fid(real_stats)
        print(f"| {spp} | {fid:.1f} | {seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
