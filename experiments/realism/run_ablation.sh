#!/usr/bin/env bash
# The classifier two-sample test (with FID beside it), train ids only, for each data source of an ablation table
# (experiments/tio2_sem/ABLATION.md, experiments/tio2_tsem/ABLATION.md): real vs real; renders of the chosen epoch of
# GAN_RUN (a), of the same scene at the network's initial weights (b), at the middle of every limit (c), at the
# probes' best fixed values (d); and the generated dataset of row a when experiments/tio2_sem/ablation.sh has made it.
# Run from the repository root:
#
#   bash experiments/realism/run_ablation.sh DATASET GAN_RUN [SEEDS]
#   bash experiments/realism/run_ablation.sh tio2_sem runs/tio2_sem/make_train_20261124c "0 1 2"
#   bash experiments/realism/run_ablation.sh tio2_tsem runs/tio2_tsem/tsem_floor003_bg080_lr1e5_every15 0
#
# Results: runs/realism/{sem,tsem}_*/results.json (a finished one is kept), tabulated by
# `python experiments/realism/collect.py runs/realism sem_` (or tsem_).
set -euo pipefail
DATASET=${1:?usage: run_ablation.sh DATASET GAN_RUN [SEEDS]}
GAN=${2:?usage: run_ablation.sh DATASET GAN_RUN [SEEDS]}
SEEDS=${3:-0}
DATA=${DRGAN_DATA:-../shared/datasets}/$DATASET
# data.* as the training runs (experiment=DATASET): stride 288 -> the same train patches (134 SEM, 126 TSEM).
case $DATASET in
  tio2_sem)
    P=sem ROWS=runs/ablation
    COMMON="data.dir=$DATA/images data.stride=288 data.crop_rows=[712,768] data.cache_dir=runs/realism/sem_patches progress=false"
    BEST='{stage:{base_color:0.2937},particle:{roughness:2.1357,base_color:0.8208,sheen:2.7366,sheen_tint:2.4281,spec_tint:2.725},noise:{sigma:0.0392}}' ;;
  tio2_tsem)
    P=tsem ROWS=runs/ablation_tsem
    COMMON="data.dir=$DATA/images data.stride=288 data.cache_dir=runs/realism/tsem_patches progress=false"
    BEST='{transmission:{background:0.8598,absorption:0.2222,floor:0.01},noise:{sigma:0.01026}}' ;;
  *) echo "DATASET: expected tio2_sem or tio2_tsem, got $DATASET" >&2; exit 2 ;;
esac
run() {  # run NAME OVERRIDES...: one test, skipped when its results.json exists
  local out=runs/realism/$1
  shift
  [ -f $out/results.json ] || python -m drgan.realism $COMMON "$@" out=$out
}
for s in $SEEDS; do
  suffix=$([ "$s" = 0 ] && echo "" || echo "_s$s")
  run ${P}_real_vs_real$suffix seed=$s synthetic=real
  run ${P}_a_trained$suffix seed=$s synthetic=$GAN
  run ${P}_b_initial$suffix seed=$s synthetic=$GAN render.parameters=initial
  run ${P}_c_middle$suffix seed=$s synthetic=$GAN render.parameters=middle
  run ${P}_d_probe$suffix seed=$s synthetic=$GAN "render.parameters=$BEST"
  if [ -f $ROWS/a/synthetic/manifest.json ]; then
    run ${P}_a_dataset$suffix seed=$s synthetic=$ROWS/a/synthetic
  fi
done
