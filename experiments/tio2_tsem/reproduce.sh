#!/usr/bin/env bash
# TiO2 TSEM (dark particles on a bright film) end to end: GAN on the 32 unannotated train images, 1,000 synthetic
# pairs + 200 real background patches, U-Net segmenters on synthetic and on real annotated train images (3 seeds
# each, the same training length as the SEM case: 6 epochs of ~1,200 crops), scores on the 8 test ids.
#
#   bash experiments/tio2_tsem/reproduce.sh [GAN_RUN_NAME] [EPOCHS]
#
# Every step resumes when run again (train: ckpt_path=last; generate: finished indices are skipped; segment:
# ckpt_path=last). Outputs under runs/tio2_tsem/ (not committed: the images are licensed no-derivatives).
set -euo pipefail
RUN=${1:-tsem_transmission}
GAN_EPOCHS=${2:-12}
DATA=${DRGAN_DATA:-../shared/datasets}/tio2_tsem
OUT=runs/tio2_tsem

# 1. The GAN (best epoch chosen as it trains; stop it any time, checkpoints/best.ckpt is the best so far).
python -m drgan.train experiment=tio2_tsem run_name=$RUN trainer.max_epochs=$GAN_EPOCHS ckpt_path=last

# 2. 1,000 synthetic pairs + 200 real background patches (from the run's mined train patches).
python -m drgan.generate ckpt=$OUT/$RUN n=1000 n_background=200 out=$OUT/synthetic

# 3. Segmenters: 3 seeds on synthetic pairs, 3 on the real train images (32 x 38 crops ~ 1,200 per epoch).
for seed in 0 1 2; do
  python -m drgan.segment data=$OUT/synthetic name=tio2_tsem_synthetic run_name=seed$seed seed=$seed \
    out=$OUT/seg_synthetic_$seed trainer.max_epochs=6 logger=none ckpt_path=last
  python -m drgan.segment real=$DATA name=tio2_tsem_real run_name=seed$seed seed=$seed \
    out=$OUT/seg_real_$seed trainer.max_epochs=6 loader.samples_per_pair=38 logger=none ckpt_path=last
done

# 4. Scores on the 8 test ids: DSC, AP50, PQ per run and mean +- std.
for kind in synthetic real; do
  python -m drgan.evaluate data=$DATA out=$OUT/eval_$kind \
    "models=[$OUT/seg_${kind}_0/checkpoints/last.ckpt,$OUT/seg_${kind}_1/checkpoints/last.ckpt,$OUT/seg_${kind}_2/checkpoints/last.ckpt]"
done
