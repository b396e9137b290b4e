#!/usr/bin/env bash
# The paper's TiO2 SEM row on the shared dataset, end to end (issue 4). Every command that made RESULTS.md.
#
#   bash experiments/tio2_sem/reproduce.sh GAN_RUN_FOLDER [EPOCHS]
#
# GAN_RUN_FOLDER: a trained DiffRenderGAN run (its checkpoints/best.ckpt is used), trained on the train ids
# only (python -m drgan.train experiment=tio2_sem ...). EPOCHS: segmenter epochs (paper-like default 25;
# RESULTS.md says what was used). Three seeds for the synthetic-trained and the real-trained segmenter,
# all scored on the 8 test ids of split.json. Outputs under runs/reproduce/ (not committed: the real images
# are licensed no-derivatives, and overlays show them).
set -euo pipefail
GAN=${1:?usage: reproduce.sh GAN_RUN_FOLDER [EPOCHS]}
EPOCHS=${2:-25}
DATA=${DRGAN_DATA:-../shared/datasets}/tio2_sem
OUT=runs/reproduce
SPP=${SPP:-121}          # generation spp (paper: 121)

# 1. 1,000 synthetic pairs + 200 real background patches (resumable: rerun to continue).
python -m drgan.generate ckpt="$GAN" n=1000 n_background=200 out=$OUT/synthetic renderer.spp=$SPP

# 2. Segmenters: 3 seeds on synthetic pairs, 3 on real train patches (same number of crops per epoch:
#    32 real images x 38 crops ~ 1,200 synthetic pairs x 1 crop).
for seed in 0 1 2; do
  python -m drgan.segment data=$OUT/synthetic name=tio2_sem_synthetic run_name=seed$seed seed=$seed \
    out=$OUT/seg_synthetic_$seed trainer.max_epochs=$EPOCHS
  python -m drgan.segment real=$DATA name=tio2_sem_real run_name=seed$seed seed=$seed \
    out=$OUT/seg_real_$seed trainer.max_epochs=$EPOCHS loader.samples_per_pair=38
done

# 3. Scores on the 8 test ids: DSC, AP50, PQ per run and mean +- std.
for kind in synthetic real; do
  python -m drgan.evaluate data=$DATA out=$OUT/eval_$kind \
    "models=[$OUT/seg_${kind}_0/checkpoints/last.ckpt,$OUT/seg_${kind}_1/checkpoints/last.ckpt,$OUT/seg_${kind}_2/checkpoints/last.ckpt]"
done
