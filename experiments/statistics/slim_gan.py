"""A GAN run folder made small enough to carry to a lent GPU for `drgan.generate` (the device tool carries 64 MiB):
the best checkpoint with the discriminator's weights in float16 (generation never runs D; the module still loads
strictly, the values converted back to float32), and the mined patches without the training patches (generation
reads only the background patches, unless `grey_spread=true`, which needs the full run folder).

    python experiments/statistics/slim_gan.py RUN_FOLDER OUT_FOLDER

OUT_FOLDER gets checkpoints/best.ckpt, checkpoints/best_epoch.json, patches/ and .hydra/; nothing is deleted from
RUN_FOLDER.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import torch

from drgan.core.checkpoint_io import load_checkpoint
from drgan.data.patches import PatchSet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("out")
    args = parser.parse_args()
    run, out = Path(args.run), Path(args.out)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    checkpoint = load_checkpoint(run / "checkpoints" / "best.ckpt", "run")
    state = checkpoint["state_dict"]
    for key, value in state.items():
        if key.startswith("discriminator.") and value.is_floating_point():
            state[key] = value.half()
    checkpoint.pop("optimizer_states", None)  # absent from best.ckpt today; never needed to generate
    torch.save(checkpoint, out / "checkpoints" / "best.ckpt")
    shutil.copy2(run / "checkpoints" / "best_epoch.json", out / "checkpoints" / "best_epoch.json")
    shutil.copytree(run / ".hydra", out / ".hydra", dirs_exist_ok=True)
    patches = PatchSet.load(run / "patches")
    patches.train = patches.train[:0]
    patches.train_ids, patches.train_positions, patches.train_counts = [], patches.train_positions[:0], np.zeros(0, int)
    patches.save(out / "patches")
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"{out}: {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
