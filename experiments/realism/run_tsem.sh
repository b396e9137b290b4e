#!/usr/bin/env bash
# The classifier two-sample test on TiO2 TSEM (train ids only): real vs real, the generated dataset, and renders of
# the untrained (epoch 0) and chosen (epoch 2) checkpoints; seeds 0-2. Results: runs/realism/*/results.json,
# tabulated by `python experiments/realism/collect.py runs/realism`. Run from the repository root.
set -euo pipefail
R=runs/tio2_tsem/tsem_transmission_v3/checkpoints
# data.* as the training run (experiment=tio2_tsem): stride 288 -> the same 126 patches of the 32 train images.
COMMON="data.dir=/work/shared/datasets/tio2_tsem/images data.stride=288 data.cache_dir=runs/realism/tsem_patches progress=false"
for s in 0 1 2; do
  suffix=$([ "$s" = 0 ] && echo "" || echo "_s$s")
  python -m drgan.realism $COMMON seed=$s synthetic=real out=runs/realism/tsem_real_vs_real$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=runs/tio2_tsem/synthetic out=runs/realism/tsem_real_vs_dataset$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$R/epochs/epoch_000.ckpt out=runs/realism/tsem_vs_epoch000$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$R/epoch_002.ckpt out=runs/realism/tsem_vs_epoch002$suffix
done
# The 128 px input check (seed 0):
python -m drgan.realism $COMMON synthetic=runs/tio2_tsem/synthetic test.input_size=128 out=runs/realism/tsem_real_vs_dataset_px128
python -m drgan.realism $COMMON synthetic=real test.input_size=128 out=runs/realism/tsem_real_vs_real_px128
