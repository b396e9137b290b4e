"""A copy of a generator run (an imported official one or a drgan.train run folder) whose material recaptures
secondary electrons (material.imaging.recapture, drgan.scene.direct): the same learned generator, rendered with
crevices and contacts darker (issue 67: do generated SEM contacts that image as real ones do separate better?).

    python experiments/statistics/with_recapture.py RUN OUT VALUE
    python -m drgan.generate ckpt=OUT renderer.integrator=direct_light_mis ...

Copies RUN to OUT and sets the recapture in every checkpoint's stored config (hyper_parameters.cfg.material.imaging).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import torch

from drgan.core.checkpoint_io import load_checkpoint
from drgan.scene.config import check_recapture


def main() -> None:
    run, out, value = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
    check_recapture(value)
    if out.exists():
        raise SystemExit(f"{out} exists: give a new folder")
    shutil.copytree(run, out)
    for path in sorted(out.glob("checkpoints/*.ckpt")):
        checkpoint = load_checkpoint(path, "ckpt")
        checkpoint["hyper_parameters"]["cfg"]["material"]["imaging"]["recapture"] = value
        torch.save(checkpoint, path)
        print(f"{path}: material.imaging.recapture={value:g}")


if __name__ == "__main__":
    main()
