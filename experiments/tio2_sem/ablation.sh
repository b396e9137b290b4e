#!/usr/bin/env bash
# One row of an ablation table (experiments/tio2_sem/ABLATION.md, experiments/tio2_tsem/ABLATION.md; issue 16): data
# from one source, three segmenters trained on it (seeds 0-2, the same settings for every row of a data set), scored
# on the 8 test ids of the data set's split.json.
#
#   bash experiments/tio2_sem/ablation.sh DATASET ROW GAN_RUN_FOLDER
#
# DATASET: tio2_sem or tio2_tsem (a folder of ../shared/datasets, or of $DRGAN_DATA).
# ROW: a (the trained generator's chosen epoch), b (the same scene and network at its initial weights),
# c (every learned parameter at the middle of its limits), d (the best fixed values the scene probes found:
# tio2_sem: an earlier run's medians, experiments/tio2_sem/README.md "Particle count"; tio2_tsem: v3's medians with
# floor 0.01, FID 128.1, experiments/tio2_tsem/README.md section 6), e (the 32 real annotated train images).
# GAN_RUN_FOLDER: a `python -m drgan.train experiment=DATASET` run (trained on the train ids only); rows b-d use its
# scene (material, limits, particles, texture) with other values.
# Outputs: runs/ablation/ROW/ (tio2_sem) or runs/ablation_tsem/ROW/ (tio2_tsem); not committed: the real images are
# licensed no-derivatives. Environment: SPP (generation, default 16), N (pairs, 1000), MAX_EPOCHS (segmenters; default
# 25 for tio2_sem, 6 for tio2_tsem as its reproduce.sh; each stops earlier when its val/loss stops falling: segment's
# early_stopping, patience 3), SEEDS (default "0 1 2"). Rerun the same command to resume an interrupted row.
# Beside other jobs on few cores, OMP_NUM_THREADS=1 (torch's threads wait on each other when oversubscribed).
set -euo pipefail
DATASET=${1:?usage: ablation.sh DATASET ROW GAN_RUN_FOLDER}
ROW=${2:?usage: ablation.sh DATASET ROW GAN_RUN_FOLDER}
GAN=${3:?usage: ablation.sh DATASET ROW GAN_RUN_FOLDER}
DATA=${DRGAN_DATA:-../shared/datasets}/$DATASET
SPP=${SPP:-16}
N=${N:-1000}
SEEDS=${SEEDS:-0 1 2}

case $DATASET in
  tio2_sem)
    OUT=runs/ablation/$ROW NAME=ablation_$ROW MAX_EPOCHS=${MAX_EPOCHS:-25}
    BEST='{stage:{base_color:0.2937},particle:{roughness:2.1357,base_color:0.8208,sheen:2.7366,sheen_tint:2.4281,spec_tint:2.725},noise:{sigma:0.0392}}' ;;
  tio2_tsem)
    OUT=runs/ablation_tsem/$ROW NAME=ablation_tsem_$ROW MAX_EPOCHS=${MAX_EPOCHS:-6}
    BEST='{transmission:{background:0.8598,absorption:0.2222,floor:0.01},noise:{sigma:0.01026}}' ;;
  *) echo "DATASET: expected tio2_sem or tio2_tsem, got $DATASET" >&2; exit 2 ;;
esac
case $ROW in
  a) PARAMETERS=trained ;;
  b) PARAMETERS=initial ;;
  c) PARAMETERS=middle ;;
  d) PARAMETERS=$BEST ;;
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
    python -m drgan.segment real=$DATA name=$NAME run_name=seed$seed seed=$seed out=$OUT/seg_$seed \
      trainer.max_epochs=$MAX_EPOCHS loader.samples_per_pair=38 trainer.enable_progress_bar=false $RESUME
  else
    if [ ! -f $OUT/synthetic/manifest.json ]; then
      python -m drgan.generate ckpt="$GAN" n=$N n_background=200 out=$OUT/synthetic renderer.spp=$SPP \
        "parameters=$PARAMETERS" progress=false
    fi
    python -m drgan.segment data=$OUT/synthetic name=$NAME run_name=seed$seed seed=$seed \
      out=$OUT/seg_$seed trainer.max_epochs=$MAX_EPOCHS trainer.enable_progress_bar=false $RESUME
  fi
done
python -m drgan.evaluate data=$DATA out=$OUT/eval "models=[$(IFS=,; echo "${models[*]}")]"
