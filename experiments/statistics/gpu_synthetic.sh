#!/usr/bin/env bash
# Synthetic-trained U-Nets on a lent GPU, as one device command: generate the pairs from GAN runs trained on the CPU
# (experiments/statistics/run.sh's gan step, or the end-to-end runs of experiments/statistics/README.md), then train
# the U-Nets of every GAN, variant and seed side by side on the one GPU; their checkpoints come back under $OUT for
# `drgan.evaluate` on the CPU (test images never travel).
#   carry:   .gpu_site.tar.xz (bash ../shared/gpu/build_site.sh) and each GAN run folder with only
#            checkpoints/best.ckpt, checkpoints/best_epoch.json, patches/ and .hydra/
#   command: GANS="sem=.gpu_gan_sem tsem=.gpu_gan_tsem" bash experiments/statistics/gpu_synthetic.sh
# Env: GANS ("default=.gpu_gan": NAME=FOLDER pairs), SEEDS ("0 1 2"), VARIANTS ("default grey_spread": generate's
# defaults, and grey_spread=true), EPOCHS (12), N (1000 pairs), N_BACKGROUND (200), WORKERS (2 loader workers per
# U-Net), THREADS (torch threads per U-Net: the machine's cores shared out; 16 threads each in six processes
# oversubscribed 16 cores), BUDGET (s for the whole command, 520).
# As run.sh's generate and segment steps, but logger=none (no MLflow on the GPU machine) and loader workers.
# Back under $OUT (the device tool returns at most 8 files of <= 16 MiB): each U-Net's last.ckpt as RUN.ckpt, and
# logs.tar in parts of 15 MiB (cat logs.tar.part_* | tar -x): every log, metrics.json, the generated sets' manifest
# and config, and HELDOUT (100) pairs per set from seed 1 for calibrate_ckpt.py when the calibration did not finish.
set -uo pipefail
OUT=${OUT:-/tmp/gpu_out}
LOGS=/tmp/gpu_logs
SEEDS=${SEEDS:-0 1 2}
VARIANTS=${VARIANTS:-default grey_spread}
GANS=${GANS:-default=.gpu_gan}
mkdir -p "$OUT" "$LOGS"
t0=$(date +%s)
deadline=$((t0 + ${BUDGET:-520}))
log() { echo "[$(($(date +%s) - t0)) s] $*" | tee -a "$LOGS/steps.txt"; }

[ -d /tmp/.gpu_site ] || tar -xJf .gpu_site.tar.xz -C /tmp
export PYTHONPATH=/tmp/.gpu_site:$PWD/src DRGAN_ROOT=/tmp/drgan_root
mkdir -p /tmp/drgan_root
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$LOGS/nvidia_smi.csv" 2>&1
log "site unpacked"

runs=()
for gan in $GANS; do
  name=${gan%%=*} folder=${gan#*=}
  for variant in $VARIANTS; do
    extra=(); [ "$variant" = grey_spread ] && extra=(grey_spread=true)
    set_=${name}_$variant
    timeout "${GEN_LIMIT:-150}" python3 -m drgan.generate ckpt="$folder" n="${N:-1000}" n_background="${N_BACKGROUND:-200}" \
      out="/tmp/synthetic_$set_" renderer.spp=16 progress=false "${extra[@]}" > "$LOGS/generate_$set_.log" 2>&1
    log "generate $set_: exit $? ($(ls "/tmp/synthetic_$set_/images" 2>/dev/null | wc -l) images)"
    mkdir -p "$LOGS/synthetic_$set_"
    cp "/tmp/synthetic_$set_/manifest.json" "/tmp/synthetic_$set_/config.json" "$LOGS/synthetic_$set_/" 2>/dev/null
    if [ "${HELDOUT:-100}" -gt 0 ]; then  # pairs from another seed that no U-Net trains on: calibrate_ckpt.py's --data
      timeout 60 python3 -m drgan.generate ckpt="$folder" n="${HELDOUT:-100}" n_background=0 seed=1 \
        out="$LOGS/heldout_$set_" renderer.spp=16 progress=false "${extra[@]}" > "$LOGS/heldout_$set_.log" 2>&1
      log "heldout $set_: exit $?"
    fi
    for seed in $SEEDS; do runs+=("$set_:$seed"); done
  done
done

limit=$((deadline - $(date +%s) - 15))
threads=${THREADS:-$(( $(nproc) / ${#runs[@]} > 0 ? $(nproc) / ${#runs[@]} : 1 ))}
log "segment: ${#runs[@]} U-Nets side by side, $threads threads each, limit $limit s"
for r in "${runs[@]}"; do
  set_=${r%%:*} seed=${r#*:}
  OMP_NUM_THREADS=$threads timeout "$limit" python3 -m drgan.segment data="/tmp/synthetic_$set_" name="gpu_$set_" \
    run_name="seed$seed" seed="$seed" out="/tmp/seg_${set_}_$seed" logger=none trainer.max_epochs="${EPOCHS:-12}" \
    trainer.enable_progress_bar=false loader.num_workers="${WORKERS:-2}" > "$LOGS/seg_${set_}_$seed.log" 2>&1 &
done
wait
log "segment: done"
for r in "${runs[@]}"; do
  run=seg_${r%%:*}_${r#*:}
  cp "/tmp/$run/checkpoints/last.ckpt" "$OUT/$run.ckpt" 2>/dev/null
  cp "/tmp/$run/metrics.json" "$LOGS/$run.metrics.json" 2>/dev/null
  log "$run: $(ls "/tmp/$run/checkpoints" 2>/dev/null | tr '\n' ' ') metrics.json: $([ -f "/tmp/$run/metrics.json" ] && echo yes || echo no)"
done
tar -cf - -C "$LOGS" . | split -b 15m - "$OUT/logs.tar.part_"
