#!/usr/bin/env bash
# Train the rest-referenced models in one timed run: simulate their data, then train the
# candidates side by side on one device until a wall-clock deadline. Made for a lent GPU
# machine (16 cores, one GPU; ../shared/gpu-checklist.md) and tried at a tiny size on the CPU.
#
#   scripts/train_rest_models.sh full OUT [DEADLINE_S]   # on the GPU machine
#   scripts/train_rest_models.sh tiny OUT [DEADLINE_S]   # a few-minute check on a CPU
#
# Runs (every exact command is echoed into OUT/commands.txt):
#   sim_a, sim_b   the built-in simulated sensor (its default build and look), mixed press
#                  profiles (holds, ramps, changes while held): candidates for sim_model.pt
#   base           builds (--variety train) and looks (--looks train) over the range, mixed
#                  profiles, colour jitter: the candidate for base_model.pt
# Continue any of them later with `beadsight train --out RUN --resume --budget-min M`.
set -uo pipefail
cd "$(dirname "$0")/.."
size=${1:?tiny or full}
out=${2:?output folder}
deadline_s=${3:-540}
start=$(date +%s)
mkdir -p "$out"
PY=${PYTHON:-python3}
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH}
log() { echo "[$(( $(date +%s) - start )) s] $*"; }
run() { echo "$*" >>"$out/commands.txt"; "$@"; }

if [ "$size" = full ]; then
  presses_a=600; pouches_a=30; presses_b=600; pouches_b=300; workers=7
  device=cuda; precision=bf16; batch=64; train_args=(--loader device)
else
  presses_a=6; pouches_a=2; presses_b=6; pouches_b=3; workers=1
  device=cpu; precision=fp32; batch=8; train_args=(--loader device --threads 1)
fi
log "simulating on $(nproc) cores"
sim=(--image-size 64 --profile mixed --workers "$workers" --no-progress)
run $PY -m beadsight simulate --out "$out/a.h5" --presses $presses_a --pouches $pouches_a \
  --seed 2300 "${sim[@]}" >"$out/simulate_a.log" 2>&1 &
run $PY -m beadsight simulate --out "$out/b.h5" --presses $presses_b --pouches $pouches_b \
  --variety train --looks train --seed 2400 "${sim[@]}" >"$out/simulate_b.log" 2>&1 &
wait
for f in a b; do [ -f "$out/$f.h5" ] || { log "simulate $f failed"; tail -5 "$out/simulate_$f.log"; exit 1; }; done
log "data ready"

# Train until the deadline, less a minute for the last validation and checkpoints.
left_min=$(python3 -c "print(max(0.5, ($deadline_s - ($(date +%s) - $start) - 60) / 60))")
log "training for $left_min min"
common=(--rest-input --dropout 0 --batch-size $batch --lr 1e-3 --lr-schedule cosine
  --split 0.95 0.05 0 --seed 0 --device $device --precision $precision --budget-min "$left_min"
  --val-every-min 1 --checkpoint-every-min 1 --val-stride 4 --no-progress "${train_args[@]}")
run $PY -m beadsight train --data "$out/a.h5" --out "$out/sim_a" --width 8 --frames 4 \
  --frame-stride 2 "${common[@]}" >"$out/train_sim_a.log" 2>&1 &
run $PY -m beadsight train --data "$out/a.h5" --out "$out/sim_b" --width 8 --frames 2 \
  --frame-stride 1 "${common[@]}" >"$out/train_sim_b.log" 2>&1 &
run $PY -m beadsight train --data "$out/b.h5" --out "$out/base" --width 16 --frames 4 \
  --frame-stride 2 --color-jitter 1 "${common[@]}" >"$out/train_base.log" 2>&1 &
wait
for r in sim_a sim_b base; do
  log "$r: $(grep -c . "$out/$r/metrics.jsonl" 2>/dev/null) metric lines; $(tail -1 "$out/train_$r.log")"
done
log "done"
