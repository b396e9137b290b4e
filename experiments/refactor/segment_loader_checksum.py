"""One sha256 of what drgan.segment feeds its segmenter, for byte-identity checks across refactors.

    PYTHONPATH=OLD/src python experiments/refactor/segment_loader_checksum.py   # then with NEW/src

For the generated pairs of runs/pipeline/tsem4 and the real tio2_tsem train ids (zscore input): which pair each
training sample comes from, the train/val counts and every validation crop. Augmented training crops draw fresh
entropy per sample by design, so they are not part of the hash."""

import hashlib

import lightning.pytorch as L

from drgan.launch.configs import compose
from drgan.segment import dataloaders, load_training_pairs

SOURCES = (["data=runs/pipeline/tsem4/generate"], ["real=../shared/datasets/tio2_tsem", "contour_px=1"])

digest = hashlib.sha256()
for source in SOURCES:
    cfg = compose([*source, "out=/tmp/segment_loader_checksum"], config_name="segment")
    pairs = load_training_pairs(cfg)
    L.seed_everything(0)
    train, val, n_train, n_val = dataloaders(cfg, pairs, "zscore")
    digest.update(train.dataset.owner.tobytes())
    for index in range(min(3, len(val.dataset))):
        for tensor in val.dataset[index]:
            digest.update(tensor.numpy().tobytes())
    digest.update(f"{n_train} {n_val} {len(train.dataset)}".encode())
print(digest.hexdigest())
