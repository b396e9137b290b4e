import hashlib, sys, torch, lightning.pytorch as L
from drgan.configs import compose
from drgan.segment import dataloaders, load_training_pairs
h = hashlib.sha256()
for over in (["data=/work/main/runs/pipeline/tsem4/generate"], ["real=/work/shared/datasets/tio2_tsem", "contour_px=1"]):
    cfg = compose([*over, "out=/tmp/x"], config_name="segment")
    pairs = load_training_pairs(cfg)
    L.seed_everything(0)
    train, val, nt, nv = dataloaders(cfg, pairs, "zscore")
    h.update(train.dataset.owner.tobytes())
    for k, batch in enumerate([]):
        for t in batch: h.update(t.numpy().tobytes())
        pass
    for k, batch in enumerate([val.dataset[i] for i in range(min(3, len(val.dataset)))]):
        for t in batch: h.update(t.numpy().tobytes())
        pass
    h.update(f"{nt} {nv} {len(train.dataset)}".encode())
print(h.hexdigest())
