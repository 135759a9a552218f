#!/usr/bin/env bash
# Continue the rest-referenced models in one timed run on a lent GPU machine (16 cores, one
# GPU; ../shared/gpu-checklist.md): the cores simulate fresh presses round after round while
# the GPU trains on the round before, so no press is seen in more than one round. Tried at a
# tiny size on the CPU first.
#
#   scripts/train_rest_models.sh full OUT [DEADLINE_S]   # on the GPU machine
#   scripts/train_rest_models.sh tiny OUT [DEADLINE_S]   # a few-minute check on a CPU
#
# Models (each round starts from the round before; round 1 from SIM_INIT / BASE_INIT):
#   sim    the built-in simulated sensor (default build and look), mixed press profiles
#          (holds, ramps, changes while held): the candidate for sim_model.pt
#   wide   a second candidate for sim_model.pt, trained from scratch on the same presses:
#          width 16, T = 6 frames at stride 2
#   base   builds (--variety train) and looks (--looks train) over the range, mixed profiles,
#          colour jitter: the candidate for base_model.pt
# Every exact command is echoed into OUT/commands.txt. The last round's folders OUT/sim_rN and
# OUT/base_rN continue with `beadsight train --out RUN --resume --budget-min M`. With RESULTS=DIR,
# each round's checkpoints and logs are also copied there as soon as the round ends.
set -uo pipefail
cd "$(dirname "$0")/.."
size=${1:?tiny or full}
out=${2:?output folder}
deadline_s=${3:-480}
sim_init=${SIM_INIT:-src/beadsight/assets/sim_model.pt}
base_init=${BASE_INIT:-models/base_rest_wip.pt}
start=$(date +%s)
mkdir -p "$out"
PY=${PYTHON:-python3}
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH}
log() { echo "[$(( $(date +%s) - start )) s] $*"; }
run() { echo "$*" >>"$out/commands.txt"; "$@"; }
elapsed() { echo $(( $(date +%s) - start )); }

if [ "$size" = full ]; then
  round_s=110; first=(100 10 180 90 5 11); each=(170 10 320 160 4 9)
  device=cuda; precision=bf16; batch=128; train_args=(--loader device)
else
  round_s=45; first=(3 1 3 2 1 1); each=(3 1 3 2 1 1)
  device=cpu; precision=fp32; batch=8; train_args=(--loader device --threads 1)
fi

# simulate ROUND SIM_PRESSES SIM_POUCHES BASE_PRESSES BASE_POUCHES SIM_WORKERS BASE_WORKERS
simulate() {
  local k=$1 opts=(--image-size 64 --profile mixed --no-progress)
  run $PY -m beadsight simulate --out "$out/sim_d$k.h5" --presses "$2" --pouches "$3" \
    --seed $((2600 + k)) --workers "$6" "${opts[@]}" >"$out/simulate_sim_d$k.log" 2>&1 &
  run $PY -m beadsight simulate --out "$out/base_d$k.h5" --presses "$4" --pouches "$5" \
    --variety train --looks train --seed $((2700 + k)) --workers "$7" "${opts[@]}" \
    >"$out/simulate_base_d$k.log" 2>&1 &
  wait
  for f in sim base; do
    [ -f "$out/${f}_d$k.h5" ] || { log "simulate ${f}_d$k failed"; tail -5 "$out/simulate_${f}_d$k.log"; exit 1; }
  done
}

# train MODEL DATA ROUND INIT BUDGET_MIN LR [EXTRA...]   (INIT "-": from scratch)
train() {
  local m=$1 data=$2 k=$3 init=$4 budget=$5 lr=$6
  shift 6
  [ "$init" = - ] && set -- --rest-input "$@" || set -- --init "$init" "$@"
  run $PY -m beadsight train --data "$out/${data}_d$((k - 1)).h5" --out "$out/${m}_r$k" \
    --dropout 0 --batch-size $batch --lr "$lr" --lr-schedule cosine --split 0.95 0.05 0 \
    --seed "$k" --device $device --precision $precision --budget-min "$budget" \
    --val-every-min 0.5 --checkpoint-every-min 0.5 --val-stride 4 --no-progress \
    "${train_args[@]}" "$@" >"$out/train_${m}_r$k.log" 2>&1
}

log "simulating round 0 on $(nproc) cores"
simulate 0 "${first[@]}"
log "round 0 data ready"
k=1; sim_ckpt=$sim_init; base_ckpt=$base_init; wide_ckpt=-
while :; do
  left=$(( deadline_s - $(elapsed) - 40 ))
  # the last round when another would not get at least half a round
  if [ $left -lt $(( round_s * 3 / 2 )) ]; then last=1; budget_s=$left; else last=0; budget_s=$round_s; fi
  [ $budget_s -lt 20 ] && break
  budget=$(python3 -c "print(round($budget_s / 60, 3))")
  for m in sim base; do
    [ -f "$out/${m}_d$((k - 1)).h5" ] || { log "no ${m}_d$((k - 1)).h5"; tail -5 "$out/simulate_${m}_d$((k - 1)).log"; exit 1; }
  done
  log "round $k: training for $budget min on round $((k - 1))'s presses (last: $last)"
  # each model trains on the presses of the round before while the cores simulate the next
  train sim sim $k "$sim_ckpt" "$budget" 3e-4 &
  if [ "$wide_ckpt" = - ]; then
    train wide sim $k - "$budget" 1e-3 --width 16 --frames 6 --frame-stride 2 &
  else
    train wide sim $k "$wide_ckpt" "$budget" 5e-4 &
  fi
  train base base $k "$base_ckpt" "$budget" 5e-4 --color-jitter 1 &
  [ $last = 0 ] && simulate $k "${each[@]}" &
  wait
  rm -f "$out/sim_d$((k - 1)).h5" "$out/base_d$((k - 1)).h5"
  for m in sim wide base; do
    [ -f "$out/${m}_r$k/last.pt" ] || { log "train ${m}_r$k failed"; tail -5 "$out/train_${m}_r$k.log"; exit 1; }
    log "$m round $k: $(grep 'val loss' "$out/train_${m}_r$k.log" | tail -1)"
  done
  sim_ckpt=$out/sim_r$k/last.pt; base_ckpt=$out/base_r$k/last.pt; wide_ckpt=$out/wide_r$k/last.pt
  if [ -n "${RESULTS:-}" ]; then
    for m in sim wide base; do
      cp "$out/${m}_r$k/last.pt" "$RESULTS/${m}_last.pt"; cp "$out/${m}_r$k/best.pt" "$RESULTS/${m}_best.pt"
    done
    tar czf "$RESULTS/logs.tgz" -C "$out" --exclude='*.pt' --exclude='*.h5' .
  fi
  [ $last = 1 ] && break
  k=$((k + 1))
done
log "done after $k rounds"
