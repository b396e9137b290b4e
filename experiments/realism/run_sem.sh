#!/usr/bin/env bash
# The classifier two-sample test (with FID beside it) on TiO2 SEM, train ids only, for each data source of the
# ablation (experiments/tio2_sem/ABLATION.md): real vs real; renders of the chosen epoch of GAN_RUN (a), of the same
# scene at the network's initial weights (b), at the middle of every limit (c), at the probes' best fixed values
# (d); and the generated dataset of row a. Run from the repository root:
#
#   bash experiments/realism/run_sem.sh GAN_RUN [SEEDS]      # e.g. runs/tio2_sem/make_train_20261124c "0 1 2"
#
# Results: runs/realism/sem_*/results.json, tabulated by `python experiments/realism/collect.py runs/realism`.
set -euo pipefail
GAN=${1:?usage: run_sem.sh GAN_RUN [SEEDS]}
SEEDS=${2:-0}
DATA=${DRGAN_DATA:-../shared/datasets}/tio2_sem
# data.* as the training run (experiment=tio2_sem): stride 288, the info bar cropped -> the same 134 train patches.
COMMON="data.dir=$DATA/images data.stride=288 data.crop_rows=[712,768] data.cache_dir=runs/realism/sem_patches progress=false"
BEST='{stage:{base_color:0.2937},particle:{roughness:2.1357,base_color:0.8208,sheen:2.7366,sheen_tint:2.4281,spec_tint:2.725},noise:{sigma:0.0392}}'
for s in $SEEDS; do
  suffix=$([ "$s" = 0 ] && echo "" || echo "_s$s")
  python -m drgan.realism $COMMON seed=$s synthetic=real out=runs/realism/sem_real_vs_real$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$GAN out=runs/realism/sem_a_trained$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$GAN render.parameters=initial out=runs/realism/sem_b_initial$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$GAN render.parameters=middle out=runs/realism/sem_c_middle$suffix
  python -m drgan.realism $COMMON seed=$s synthetic=$GAN "render.parameters=$BEST" out=runs/realism/sem_d_probe$suffix
  if [ -f runs/ablation/a/synthetic/manifest.json ]; then
    python -m drgan.realism $COMMON seed=$s synthetic=runs/ablation/a/synthetic out=runs/realism/sem_a_dataset$suffix
  fi
done
