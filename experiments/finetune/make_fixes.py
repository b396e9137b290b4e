"""The correction loop's measurement (issue 66): N annotated *train* images of a dataset as a user's corrected outlines.

    python experiments/finetune/make_fixes.py DATASET N SEED OUT

Chooses N of DATASET's split.json train ids (seeded by SEED: each seed corrects other images), writes their masks'
particles as label TIFFs OUT/ID.tif (as napari saves an edited labels layer; the info bar's rows dropped as drgan
reads the image) and OUT/split.json (those train ids, the dataset's test ids): the real-only baseline trains on the
same images (`segment real=DATASET split=OUT/split.json`). Test ids are never chosen.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from drgan.data.imagej import write_label_tiff
from drgan.segmenters.pairs import load_real_items


def main() -> None:
    dataset, n, seed, out = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
    split = json.loads((dataset / "split.json").read_text())
    train = sorted(split["train"])
    chosen = sorted(np.random.default_rng((seed, 66)).choice(train, size=n, replace=False).tolist())
    assert not set(chosen) & set(split["test"])
    for item, labels in load_real_items(dataset, chosen):
        write_label_tiff(out / f"{item.id}.tif", labels)
    (out / "split.json").write_text(json.dumps({"train": chosen, "test": split["test"]}))
    print(" ".join(chosen))


if __name__ == "__main__":
    main()
