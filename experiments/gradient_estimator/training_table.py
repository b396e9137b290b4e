"""Per-epoch FID, brightness and mean learned parameters of training runs (the grad_seed comparison).

    python experiments/gradient_estimator/training_table.py runs/tio2_sem/grad_seed_same runs/tio2_sem/grad_seed_independent

FID, KID and brightness (synthetic / real mean grey) come from each run's checkpoints/best_epoch.json history;
the parameter means are the generator's outputs, in the configured units, over the same 1000 constellations
(seed 0) for every epoch checkpoint in checkpoints/epochs/ (the question is whether one estimator drifts
towards darker, rougher particles).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from omegaconf import OmegaConf

from drgan.models import build
from drgan.synthetic.source import checkpoint_config, load_module


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (runs/<material>/<run_name>)")
    parser.add_argument("--n-phi", type=int, default=1000)
    args = parser.parse_args()
    print(f"command: python {' '.join(sys.argv)}\n")
    header_done = False
    for run in args.runs:
        history = {h["epoch"]: h for h in json.loads((run / "checkpoints" / "best_epoch.json").read_text())["history"]}
        phi = None
        for ckpt in sorted((run / "checkpoints" / "epochs").glob("epoch_*.ckpt")):
            cfg = checkpoint_config(ckpt)
            module = load_module(ckpt, cfg)
            if phi is None:
                phi = build.sample_phi(OmegaConf.create(cfg), args.n_phi, seed=0)
            means = module.parameter_samples(phi).mean(0)
            keys = [p.key for p in module.generator.learned]
            if not header_done:
                print("| run | grad_seed | epoch | FID | KID | brightness | " + " | ".join(keys) + " |")
                print("|---|---|---|---|---|---|" + "---|" * len(keys))
                header_done = True
            epoch = int(ckpt.stem.split("_")[1])
            h = history.get(epoch, {})
            print(
                f"| {run.name} | {cfg['renderer'].get('grad_seed', 'same (absent)')} | {epoch} | {h.get('fid', float('nan')):.1f} "
                f"| {h.get('kid', float('nan')):.3f} | {h.get('brightness', float('nan')):.2f} | "
                + " | ".join(f"{m:.3f}" for m in means)
                + " |",
                flush=True,
            )


if __name__ == "__main__":
    main()
