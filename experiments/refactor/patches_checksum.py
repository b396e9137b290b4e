"""sha256 of drgan.data.patches.mine_patches' output on 8 tio2_sem train images, both polarities (scale pinned), for a
before/after refactor check: `[PYTHONPATH=BEFORE/src] python experiments/refactor/patches_checksum.py`."""

import hashlib
import json
from pathlib import Path

import numpy as np

from drgan.data.images import read_grey
from drgan.data.patches import mine_patches

root = Path("../shared/datasets/tio2_sem")
ids = json.loads((root / "split.json").read_text())["train"][:8]
paths = [next((root / "images").glob(f"{i}.*")) for i in ids]
images = [read_grey(p, "auto") for p in paths]
for polarity, bg in (("bright", 40), ("dark", 5)):
    ps = mine_patches(
        images, ids, 256, 128, 3, bg, segment={"scale": 27.55, "neck_depth": 0.2}, polarity=polarity, progress=False
    )
    h = hashlib.sha256()
    for a in (ps.train, ps.train_positions, ps.train_counts, ps.background, ps.background_positions):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([ps.train_ids, ps.background_ids, ps.params], sort_keys=True, default=str).encode())
    print(polarity, len(ps.train), len(ps.background), h.hexdigest())
