#!/usr/bin/env bash
# FID of each synthetic row of an ablation table (experiments/tio2_sem/ABLATION.md, experiments/tio2_tsem/ABLATION.md)
# at the datasets' spp 16, over three draws (the phi bank, then two new banks with their own render seeds), against
# the real train patches of GAN_RUN (134 for tio2_sem, 126 for tio2_tsem):
#
#   bash experiments/tio2_sem/ablation_fid.sh DATASET GAN_RUN > runs/ablation/fid.md     # DATASET: tio2_sem or tio2_tsem
#
# Rows a-d as experiments/tio2_sem/ablation.sh (a trained, b initial weights, c middle of the limits, d the probes' values).
set -euo pipefail
DATASET=${1:?usage: ablation_fid.sh DATASET GAN_RUN}
GAN=${2:?usage: ablation_fid.sh DATASET GAN_RUN}
CKPT=$GAN/checkpoints/best.ckpt
case $DATASET in
  tio2_sem) BEST='{"stage.base_color": 0.2937, "particle.roughness": 2.1357, "particle.base_color": 0.8208, "particle.sheen": 2.7366, "particle.sheen_tint": 2.4281, "particle.spec_tint": 2.725, "noise.sigma": 0.0392}' ;;
  tio2_tsem) BEST='{"transmission.background": 0.8598, "transmission.absorption": 0.2222, "transmission.floor": 0.01, "noise.sigma": 0.01026}' ;;
  *) echo "DATASET: expected tio2_sem or tio2_tsem, got $DATASET" >&2; exit 2 ;;
esac
for row in a b c d; do
  case $row in a) P=trained ;; b) P=initial ;; c) P=middle ;; d) P=$BEST ;; esac
  echo "## row $row"
  python benchmarks/fid_vs_spp.py "$CKPT" --spp 16 --draws 3 --parameters "$P"
done
