#!/bin/bash
# Wall time of `drgan.generate` for 24 images per imported case, start-up included: the measure the official
# test_gan.py's times in ../shared/official/reference/README.md use (24 images, quiet 2-core CPU).
# Usage (repository root, a quiet machine): bash experiments/official_import/speed.sh RUNS OUT
set -euo pipefail
RUNS=${1:-runs/official}
OUT=${2:-runs/official/speed}
for tag in Mill2021TiO2_paper Mill2021SiO2_paper Ruehle2021TiO2_paper Ag_paper; do
  rm -rf "$OUT/$tag"
  start=$(date +%s.%N)
  python -m drgan.generate ckpt="$RUNS/$tag" out="$OUT/$tag" n=24 n_background=0 min_background=0.15 \
    progress=false > /dev/null 2>&1
  end=$(date +%s.%N)
  kept=$(ls "$OUT/$tag/images" | wc -l)
  echo "$tag: $(echo "$end - $start" | bc) s for $kept images"
done
