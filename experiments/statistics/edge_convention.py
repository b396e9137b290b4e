"""Where masks put the particle edge against half contrast: real annotations and drgan's generated masks alike.

The mean particle edge (drgan.synthetic.edge_check: the profile's edge measurement, isolated particles only) against
each set's own masks: ``half_px`` is where the grey crosses half the particle contrast, px from the mask edge (> 0:
half contrast lies outside the mask, the mask is drawn inside the visible outline); ``width_px`` the 10-90 % ramp.

    python experiments/statistics/edge_convention.py --real ../shared/datasets/tio2_tsem --ids train \
        --generated runs/pipeline/bam_tio2_tsem/generate
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from drgan.segmenters.pairs import load_generated_pairs, load_real, real_ids
from drgan.synthetic.edge_check import edge_of


def report(name: str, images, labels) -> None:
    ramp = edge_of(images, lambda k: labels[k], lambda k: labels[k] > 0)
    if ramp is None:
        print(f"{name}: too few isolated particles")
        return
    print(json.dumps({"set": name, **{k: ramp[k] for k in ("particles", "half_px", "width_px", "ring")}}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", action="append", default=[])
    parser.add_argument("--ids", default="train")
    parser.add_argument("--generated", action="append", default=[])
    parser.add_argument("--n", type=int, default=64)
    args = parser.parse_args()
    for folder in args.real:
        items = load_real(folder, real_ids(folder, None, args.ids))
        report(
            f"{folder} ({args.ids} annotations)", [np.asarray(i, float) for _, i, _ in items], [m for *_, m in items]
        )
    for folder in args.generated:
        pairs = [p for p in load_generated_pairs(folder) if p.labels is not None][: args.n]
        report(f"{folder} (exact masks)", [np.asarray(p.image, float) for p in pairs], [p.labels for p in pairs])


if __name__ == "__main__":
    main()
