#!/usr/bin/env bash
# Issue 29's end-to-end check on one BAM set, as a user runs it on their own images: the profile of the train ids
# writes a material, the GAN trains with it (nothing set by hand but the recorded runs' time budget: an evaluation
# every 67 steps, 27 minutes), then 1,000 generated pairs, U-Nets (3 seeds) and drgan.evaluate on the test ids, as
# run.sh does for the recorded rows (experiments/statistics/chain.md, "End to end").
#
#   bash experiments/statistics/e2e.sh tio2_sem|tio2_tsem [OUT]          # profile and GAN (CPU, ~30 min each)
#   STEPS="generate segment evaluate" KINDS=synthetic bash experiments/statistics/run.sh SET OUT   # the rest (CPU)
#
# or the rest on a lent GPU: slim_gan.py OUT/gan .gpu_gan_e2e_SET, gpu_synthetic.sh with
# GANS="e2e_SET=.gpu_gan_e2e_SET" VARIANTS=default, calibrate_ckpt.py and drgan.evaluate here.
# Everything is written under OUT (default runs/e2e/SET); the material goes to OUT/drgan_conf/material/e2e_SET.yaml.
set -euo pipefail
SET=${1:?usage: e2e.sh tio2_sem|tio2_tsem [OUT]}
OUT=$(mkdir -p "${2:-runs/e2e/$SET}" && cd "${2:-runs/e2e/$SET}" && pwd)
DATA=$(cd "${DRGAN_DATA:-../shared/datasets}/$SET" && pwd)
MINUTES=${MINUTES:-27}
cd "$OUT"  # the profile writes ./drgan_conf/material/, which drgan.train finds from the folder it runs in
[ -f "drgan_conf/material/e2e_$SET.yaml" ] ||
  python -m drgan.profile data.dir="$DATA/images" name="e2e_$SET" out="$OUT/profile" overwrite=true
if [ ! -f gan/checkpoints/best.ckpt ]; then
  resume=(); [ -f gan/checkpoints/last.ckpt ] && resume=(ckpt_path=last)
  python -m drgan.train material="e2e_$SET" hydra.run.dir="$OUT/gan" trainer.limit_train_batches=67 \
    callbacks.early_stopping.max_minutes="$MINUTES" "${resume[@]}"
fi
