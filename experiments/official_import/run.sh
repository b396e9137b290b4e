#!/bin/bash
# Import the four published official generators, generate 200 images each, compare with the official references.
# Usage (from the repository root): bash experiments/official_import/run.sh [OFFICIAL] [RUNS]
set -euo pipefail
OFFICIAL=${1:-../shared/official}
RUNS=${2:-runs/official}
export PYTHONPATH=src
for tag in Mill2021TiO2_paper Mill2021SiO2_paper Ruehle2021TiO2_paper Ag_paper; do
  python -m drgan.import_official official="$OFFICIAL/experiments/$tag" out="$RUNS/$tag"
  # min_background=0.15: the official test_gan.py's --bg_portion; no real images, so no background patches
  nice -n 10 python -m drgan.generate ckpt="$RUNS/$tag" out="$RUNS/gen_$tag" n=200 n_background=0 \
    min_background=0.15 progress=false
done
python experiments/official_import/compare.py --official "$OFFICIAL" --runs "$RUNS" --out experiments/official_import
