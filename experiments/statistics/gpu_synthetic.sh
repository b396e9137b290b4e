#!/usr/bin/env bash
# Issue 27's synthetic-trained U-Nets on a lent GPU, as one device command: generate the pairs from a GAN run trained on
# the CPU (experiments/statistics/run.sh's gan step), then train the U-Nets of every seed and variant side by side on
# the one GPU; their checkpoints come back under $OUT for `drgan.evaluate` on the CPU (test images never travel).
#   carry:   .gpu_site.tar.xz (bash ../shared/gpu/build_site.sh) and .gpu_gan: the GAN run folder with only
#            checkpoints/best.ckpt, checkpoints/best_epoch.json, patches/ and .hydra/
#   command: bash experiments/statistics/gpu_synthetic.sh
# Env: SEEDS ("0 1 2"), VARIANTS ("default grey_spread": generate's defaults, and grey_spread=true), EPOCHS (12),
# N (1000 pairs), N_BACKGROUND (200), WORKERS (2 loader workers per U-Net), BUDGET (s for the whole command, 520).
# As run.sh's generate and segment steps, but logger=none (no MLflow on the GPU machine) and loader workers.
set -uo pipefail
OUT=${OUT:-/tmp/gpu_out}
SEEDS=${SEEDS:-0 1 2}
VARIANTS=${VARIANTS:-default grey_spread}
mkdir -p "$OUT"
t0=$(date +%s)
deadline=$((t0 + ${BUDGET:-520}))
log() { echo "[$(($(date +%s) - t0)) s] $*" | tee -a "$OUT/steps.txt"; }

tar -xJf .gpu_site.tar.xz -C /tmp
export PYTHONPATH=/tmp/.gpu_site:$PWD/src DRGAN_ROOT=/tmp/drgan_root
mkdir -p /tmp/drgan_root
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$OUT/nvidia_smi.csv" 2>&1
log "site unpacked"

for variant in $VARIANTS; do
  extra=(); [ "$variant" = grey_spread ] && extra=(grey_spread=true)
  timeout "${GEN_LIMIT:-150}" python3 -m drgan.generate ckpt=.gpu_gan n="${N:-1000}" n_background="${N_BACKGROUND:-200}" \
    out="/tmp/synthetic_$variant" renderer.spp=16 progress=false "${extra[@]}" > "$OUT/generate_$variant.log" 2>&1
  log "generate $variant: exit $? ($(ls "/tmp/synthetic_$variant/images" 2>/dev/null | wc -l) images)"
  mkdir -p "$OUT/synthetic_$variant"
  cp "/tmp/synthetic_$variant/manifest.json" "/tmp/synthetic_$variant/config.json" "$OUT/synthetic_$variant/" 2>/dev/null
done

limit=$((deadline - $(date +%s) - 15))
log "segment: $(echo $VARIANTS | wc -w) variants x $(echo $SEEDS | wc -w) seeds side by side, limit $limit s"
for variant in $VARIANTS; do
  for seed in $SEEDS; do
    run=seg_${variant}_$seed
    timeout "$limit" python3 -m drgan.segment data="/tmp/synthetic_$variant" name="stats_gpu_$variant" run_name="seed$seed" \
      seed="$seed" out="/tmp/$run" logger=none trainer.max_epochs="${EPOCHS:-12}" trainer.enable_progress_bar=false \
      loader.num_workers="${WORKERS:-2}" > "$OUT/$run.log" 2>&1 &
  done
done
wait
log "segment: done"
for variant in $VARIANTS; do
  for seed in $SEEDS; do
    run=seg_${variant}_$seed
    mkdir -p "$OUT/$run/checkpoints"
    cp "/tmp/$run/checkpoints/last.ckpt" "$OUT/$run/checkpoints/" 2>/dev/null
    cp "/tmp/$run/metrics.json" "$OUT/$run/" 2>/dev/null
    log "$run: $(ls "/tmp/$run/checkpoints" 2>/dev/null | tr '\n' ' ') metrics.json: $([ -f "/tmp/$run/metrics.json" ] && echo yes || echo no)"
  done
done
