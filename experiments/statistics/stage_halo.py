"""Is the background darker next to particles? (issue 67: does the recapture's stage halo exist in real images?)

    python experiments/statistics/stage_halo.py --real ../shared/datasets/tio2_sem --generated GEN [GEN ...]

Per image: the background's median grey in rings 2-4 and 4-8 px outside the particles (distance to the nearest
particle pixel) over its median beyond 12 px, as a ratio; quartiles over images. Real: the train ids' annotated masks;
generated: the pairs' exact labels.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from drgan.segmenters.pairs import load_generated_pairs, load_real_items

RINGS = ((2, 4), (4, 8))


def ratios(image: np.ndarray, particles: np.ndarray) -> list[float] | None:
    distance = ndi.distance_transform_edt(~particles)
    far = image[distance > 12]
    if far.size < 500:
        return None
    base = float(np.median(far))
    out = []
    for low, high in RINGS:
        ring = image[(distance > low) & (distance <= high)]
        out.append(float(np.median(ring)) / base if ring.size >= 50 and base > 0 else float("nan"))
    return out


def row(name: str, items) -> str:
    values = np.array([r for r in items if r is not None])
    cells = [" / ".join(f"{q:.3f}" for q in np.nanpercentile(values[:, k], [25, 50, 75])) for k in range(len(RINGS))]
    return f"| {name} | {len(values)} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real")
    parser.add_argument("--generated", nargs="*", default=[])
    args = parser.parse_args()
    print("| images | n | ring 2-4 px / far: quartiles | ring 4-8 px / far |")
    print("|---|---|---|---|")
    if args.real:
        ids = json.loads((Path(args.real) / "split.json").read_text())["train"]
        items = load_real_items(args.real, ids)
        found = [ratios(np.asarray(item.image, float), np.asarray(labels) > 0) for item, labels in items]
        print(row(f"real masks ({args.real}, train ids)", found))
    for folder in args.generated:
        pairs = [p for p in load_generated_pairs(folder, setting="data") if str(p.id).startswith("syn_")]
        found = [ratios(np.asarray(p.image, float), np.asarray(p.instances()) > 0) for p in pairs]
        print(row(f"generated ({folder})", found))


if __name__ == "__main__":
    main()
