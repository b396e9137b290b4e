"""FID of one trained generator rendered at several spp, and over several draws: how much of the FID is
Monte Carlo noise, and how much a score moves with the images drawn.

    python benchmarks/fid_vs_spp.py runs/tio2_sem/tio2_sem_spp16/checkpoints/last.ckpt --spp 4 16 64
    python benchmarks/fid_vs_spp.py runs/tio2_sem/<run>/checkpoints/best.ckpt --spp 121 --draws 3
    python benchmarks/fid_vs_spp.py runs/tio2_sem/<run>/checkpoints/best.ckpt --spp 16 --draws 3 --parameters middle

Renders as many images as real training patches at each spp and scores them against the real training
patches (clean-resized Inception features). Draw 0 is the checkpoint's phi bank with render seeds 10000+;
draw d > 0 samples a new bank of constellations (seed d) and uses render seeds 10000 + d * 100000 + i.
``--parameters``: the scene values (as `drgan.generate parameters=`): trained (default), initial, middle, or a
JSON mapping of every learned parameter, e.g. '{"particle.roughness": 0.5, ...}' (the ablations' controls).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from drgan.data.patches import PatchSet
from drgan.metrics.feature_distances import FeatureStats
from drgan.metrics.inception import InceptionFeatures
from drgan.models.gan_module import GANModule
from drgan.synthetic.generation_settings import parameter_source
from drgan.synthetic.source import checkpoint_config, use_parameters


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path)
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--draws", type=int, default=1, help="image sets per spp (phi bank and render seeds)")
    parser.add_argument("--parameters", default="trained", help="trained | initial | middle | a JSON mapping")
    args = parser.parse_args()
    parameters = parameter_source(json.loads(args.parameters) if args.parameters.startswith("{") else args.parameters)
    # The run folder holds patches/: checkpoints/last.ckpt or checkpoints/epochs/epoch_XXX.ckpt.
    run = next((p for p in args.ckpt.resolve().parents if (p / "patches").is_dir()), None)
    if run is None:
        sys.exit(f"{args.ckpt}: no run folder with patches/ above it (expected <run>/checkpoints/...ckpt)")
    real = PatchSet.load(run / "patches").train
    extractor = InceptionFeatures(batch_size=16)
    real_stats = FeatureStats.from_features(extractor.features(real))
    module = GANModule.load_from_checkpoint(args.ckpt, map_location="cpu")
    module.eval()
    use_parameters(module, parameters, checkpoint_config(args.ckpt))
    if module.textured:  # the stage texture of training, from the same run's background patches
        module.use_background_texture(PatchSet.load(run / "patches").background)
    print(f"command: python {' '.join(sys.argv)}\ncheckpoint epoch: see {args.ckpt.name}; {len(real)} real patches")
    print(f"scene values: {parameters}\n")
    print("| spp | draw | FID | render s |")
    print("|---|---|---|---|")
    for spp in args.spp:
        scores = []
        for draw in range(args.draws):
            start = time.perf_counter()
            bank = module.phi_bank if draw == 0 else torch.as_tensor(module.layouts(len(real), draw))
            images = np.stack(
                [
                    module.generator.sample(bank[i % len(bank)], seed=10_000 + draw * 100_000 + i, spp=spp).image
                    for i in range(len(real))
                ]
            )
            seconds = time.perf_counter() - start
            scores.append(FeatureStats.from_features(extractor.features(images)).fid(real_stats))
            print(f"| {spp} | {draw} | {scores[-1]:.1f} | {seconds:.0f} |", flush=True)
        if len(scores) > 1:
            print(f"| {spp} | mean +- std | {np.mean(scores):.1f} +- {np.std(scores, ddof=1):.1f} | |", flush=True)


if __name__ == "__main__":
    main()
