#!/usr/bin/env bash
# FID of each synthetic row of the ablation (experiments/tio2_sem/ABLATION.md) at the datasets' spp 16, over three
# draws of 134 images (the phi bank, then two new banks with their own render seeds), against the 134 real train
# patches of GAN_RUN:   bash experiments/tio2_sem/ablation_fid.sh GAN_RUN > runs/ablation/fid.md
set -euo pipefail
GAN=${1:?usage: ablation_fid.sh GAN_RUN}
CKPT=$GAN/checkpoints/best.ckpt
BEST='{"stage.base_color": 0.2937, "particle.roughness": 2.1357, "particle.base_color": 0.8208, "particle.sheen": 2.7366, "particle.sheen_tint": 2.4281, "particle.spec_tint": 2.725, "noise.sigma": 0.0392}'
for row in a b c d; do
  case $row in a) P=trained ;; b) P=initial ;; c) P=middle ;; d) P=$BEST ;; esac
  echo "## row $row"
  python benchmarks/fid_vs_spp.py "$CKPT" --spp 16 --draws 3 --parameters "$P"
done
