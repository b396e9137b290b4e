"""Grey levels of each ablation row's synthetic pairs beside the real annotated train images (TSEM, issue 16):
does the segmenter see a different task when the scene's values change?

    python experiments/tio2_tsem/row_greys.py [ROWS_DIR] [DATASET]   # runs/ablation_tsem, ../shared/datasets/tio2_tsem

Per image: the median grey of particle pixels (class 1) and of the rest (film), their ratio film / particle (the
transmission contrast), and the std of the film grey (noise and texture). Synthetic: the generated pairs' exact
masks (syn_* only, not the real background patches); real: the train ids' masks (test ids are not read).
Prints the median and the 10th-90th percentile range of each over the images of a source.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from drgan.scene.labels import class_mask
from drgan.segmenters.pairs import load_generated_pairs, load_real, real_ids


def stats(pairs) -> dict[str, np.ndarray]:
    rows = []
    for image, classes in pairs:
        particle, film = image[classes == 1], image[classes == 0]
        if particle.size < 20 or film.size < 20:
            continue
        p, f = np.median(particle), np.median(film)
        rows.append((p, f, f / max(p, 1e-3), film.std()))
    return dict(zip(("particle grey", "film grey", "film / particle", "film std"), np.array(rows).T))


def main():
    rows_dir = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/ablation_tsem")
    data = Path(sys.argv[2] if len(sys.argv) > 2 else "../shared/datasets/tio2_tsem")
    sources = {}
    ids = real_ids(data, None, "train")
    sources["real (32 train images)"] = stats((img, class_mask(lab, 0)) for _, img, lab in load_real(data, ids))
    for row in sorted(p.name for p in rows_dir.iterdir() if (p / "synthetic" / "manifest.json").is_file()):
        pairs = [p for p in load_generated_pairs(rows_dir / row / "synthetic") if p.id.startswith("syn_")]
        sources[f"row {row} ({len(pairs)} synthetic)"] = stats((p.image, p.mask) for p in pairs)
    keys = list(next(iter(sources.values())))
    print("| source | " + " | ".join(f"{k}: median [p10, p90]" for k in keys) + " |")
    print("|---|" + "---|" * len(keys))
    for name, s in sources.items():
        cells = [f"{np.median(s[k]):.3f} [{np.percentile(s[k], 10):.3f}, {np.percentile(s[k], 90):.3f}]" for k in keys]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
