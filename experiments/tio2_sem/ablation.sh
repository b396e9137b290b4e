#!/usr/bin/env bash
# One row of the ablation table (experiments/tio2_sem/ABLATION.md): data from one source, three segmenters
# trained on it (seeds 0-2, same settings for every row), scored on the 8 test ids of split.json.
#
#   bash experiments/tio2_sem/ablation.sh ROW GAN_RUN_FOLDER
#
# ROW: a (the trained generator's chosen epoch), b (the same scene and network at its initial weights),
# c (every learned parameter at the middle of its limits), d (the best fixed values the probes found,
# experiments/tio2_sem/README.md "Particle count"), e (the 32 real annotated train images).
# GAN_RUN_FOLDER: a `python -m drgan.train experiment=tio2_sem` run (trained on the train ids only); rows b-d
# use its scene (material, particles, texture) with other values. Outputs: runs/ablation/ROW/ (not committed:
# the real images are licensed no-derivatives). Environment: SPP (generation, default 16), N (pairs, 1000),
# MAX_EPOCHS (segmenters, default 25; each stops earlier when its val/loss stops falling: segment's
# early_stopping, patience 3), SEEDS (default "0 1 2"). Rerun the same command to resume an interrupted row.
# Beside other jobs on few cores, OMP_NUM_THREADS=1 (torch's threads wait on each other when oversubscribed).
set -euo pipefail
ROW=${1:?usage: ablation.sh ROW GAN_RUN_FOLDER}
GAN=${2:?usage: ablation.sh ROW GAN_RUN_FOLDER}
DATA=${DRGAN_DATA:-../shared/datasets}/tio2_sem
OUT=runs/ablation/$ROW
SPP=${SPP:-16}
N=${N:-1000}
MAX_EPOCHS=${MAX_EPOCHS:-25}
SEEDS=${SEEDS:-0 1 2}

case $ROW in
  a) PARAMETERS=trained ;;
  b) PARAMETERS=initial ;;
  c) PARAMETERS=middle ;;
  d) PARAMETERS='{stage:{base_color:0.2937},particle:{roughness:2.1357,base_color:0.8208,sheen:2.7366,sheen_tint:2.4281,spec_tint:2.725},noise:{sigma:0.0392}}' ;;
  e) PARAMETERS= ;;
  *) echo "ROW: expected one of a b c d e, got $ROW" >&2; exit 2 ;;
esac

models=()
for seed in $SEEDS; do
  models+=("$OUT/seg_$seed/checkpoints/last.ckpt")
  # resumable: a finished segmenter (metrics.json) is kept, an interrupted one goes on from its last.ckpt
  [ -f $OUT/seg_$seed/metrics.json ] && continue
  RESUME=$([ -f $OUT/seg_$seed/checkpoints/last.ckpt ] && echo ckpt_path=last || true)
  if [ "$ROW" = e ]; then
    # 32 real train images (29 train / 3 validation), 38 random crops each per epoch ~ 1,200 synthetic pairs
    python -m drgan.segment real=$DATA name=ablation_$ROW run_name=seed$seed seed=$seed out=$OUT/seg_$seed \
      trainer.max_epochs=$MAX_EPOCHS loader.samples_per_pair=38 trainer.enable_progress_bar=false $RESUME
  else
    if [ ! -f $OUT/synthetic/manifest.json ]; then
      python -m drgan.generate ckpt="$GAN" n=$N n_background=200 out=$OUT/synthetic renderer.spp=$SPP \
        "parameters=$PARAMETERS" progress=false
    fi
    python -m drgan.segment data=$OUT/synthetic name=ablation_$ROW run_name=seed$seed seed=$seed \
      out=$OUT/seg_$seed trainer.max_epochs=$MAX_EPOCHS trainer.enable_progress_bar=false $RESUME
  fi
done
python -m drgan.evaluate data=$DATA out=$OUT/eval "models=[$(IFS=,; echo "${models[*]}")]"
