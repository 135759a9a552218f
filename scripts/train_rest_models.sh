#!/usr/bin/env bash
# Train rest-referenced models in one timed run on a lent GPU machine (16 cores, one GPU;
# ../shared/gpu-checklist.md): the cores simulate fresh presses round after round while the
# GPU trains every model of a set, concurrently, on the round before, so no press is seen in
# more than one round. Tried at a tiny size on the CPU first.
#
#   scripts/train_rest_models.sh full OUT [DEADLINE_S] [SET]   # on the GPU machine
#   scripts/train_rest_models.sh tiny OUT [DEADLINE_S] [SET]   # a few-minute check on a CPU
#   scripts/train_rest_models.sh cpu OUT [DEADLINE_S] [SET]    # hours in the background on a
#       2-core CPU with no GPU: one model (set base), one core training it, the other
#       simulating; continue a later session's run from this one's last round with
#       BASE_INIT=OUT/base_rN/final.pt (RESULTS=DIR writes it)
#
# Sets of models (each round starts from the round before; round 1 from the model's init):
#   rest (default): the candidates for the shipped models
#     sim    the built-in simulated sensor (default build and look), mixed press profiles
#            (holds, ramps, changes while held), from SIM_INIT: the candidate for sim_model.pt
#     wide   a second candidate for sim_model.pt from scratch: width 16, T = 6 at stride 2
#     base   builds (--variety train) and looks (--looks train) over the range, mixed
#            profiles, colour jitter, from BASE_INIT: the candidate for base_model.pt
#   looks: what makes a base model over looks generalise, on the same base presses and budget
#     chan      rest input as rest + change channels (no --rest-norm), from scratch
#     norm      contrast-normalised rest input (--rest-norm), from scratch
#     norm_nj   the same without colour jitter
#     norm_wip  contrast-normalised, from BASE_INIT (the shipped base_model.pt came from this
#               model of the set's first run; base_model.md has that run's figures)
# Every exact command is echoed into OUT/commands.txt. The last round's folders OUT/NAME_rN
# continue with `beadsight train --out RUN --resume --budget-min M`. SEED_OFFSET=N moves the
# simulation seeds (2600+k, 2700+k) by N, for presses no earlier run trained on; BASE_LR
# sets the base set's learning rate (5e-5: at 2e-4 a CPU round of base_model.pt traded its
# reference presses' force error, 13.6 -> 17.0 %, for the held presses'). With RESULTS=DIR, each
# round's checkpoints are also copied there as soon as the round ends: NAME.tar holds best.pt
# and final.pt (the last step's weights, without the optimizer state: continue it with
# --init), beside logs.tgz.
set -uo pipefail
cd "$(dirname "$0")/.."
size=${1:?tiny, cpu or full}
case $size in tiny | cpu | full) ;; *) echo "size must be tiny, cpu or full, got $size" >&2; exit 2 ;; esac
out=${2:?output folder}
deadline_s=${3:-480}
set_name=${4:-rest}
sim_init=${SIM_INIT:-src/beadsight/assets/sim_model.pt}
base_init=${BASE_INIT:-src/beadsight/assets/base_model.pt}
seed_offset=${SEED_OFFSET:-0}
start=$(date +%s)
mkdir -p "$out"
PY=${PYTHON:-python3}
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH}
log() { echo "[$(( $(date +%s) - start )) s] $*"; }
run() { echo "$*" >>"$out/commands.txt"; "$@"; }
elapsed() { echo $(( $(date +%s) - start )); }

# NAME DATA INIT LR [EXTRA...]: data "sim" or "base"; init "-" trains from scratch (the
# extra arguments then give the shape); from round 2 on each model continues its last round
# (--init, its shape kept) at the same LR, with only its colour jitter repeated.
case $set_name in
  rest) models=(
    "sim sim $sim_init 3e-4"
    "wide sim - 1e-3 --rest-input --width 16 --frames 6 --frame-stride 2"
    "base base $base_init 5e-4 --color-jitter 1") ;;
  looks) models=(
    "chan base - 1e-3 --rest-input --width 16 --frames 4 --frame-stride 2 --color-jitter 1"
    "norm base - 1e-3 --rest-input --rest-norm --width 16 --frames 4 --frame-stride 2 --color-jitter 1"
    "norm_nj base - 1e-3 --rest-input --rest-norm --width 16 --frames 4 --frame-stride 2"
    "norm_wip base $base_init 5e-4 --rest-norm --color-jitter 1") ;;
  base) models=("base base $base_init ${BASE_LR:-5e-5} --color-jitter 1") ;;
  *) echo "set must be rest, looks or base, got $set_name" >&2; exit 2 ;;
esac
names=(); for m in "${models[@]}"; do names+=("${m%% *}"); done
need_sim=0; for m in "${models[@]}"; do read -r _ d _ <<<"$m"; [ "$d" = sim ] && need_sim=1; done

val_min=0.5
if [ "$size" = full ]; then
  round_s=110; first=(100 10 180 90 5 11); each=(170 10 320 160 4 9)
  device=cuda; precision=bf16; batch=128; train_args=(--loader device)
  [ $need_sim = 0 ] && first=(0 0 240 120 0 16) && each=(0 0 300 150 0 12)
elif [ "$size" = cpu ]; then
  round_s=1500; first=(100 20 200 100 1 1); each=(100 20 200 100 1 1)
  device=cpu; precision=fp32; batch=64; train_args=(--loader device --threads 1); val_min=5
  [ $need_sim = 0 ] && first=(0 0 200 100 0 2) && each=(0 0 200 100 0 1)
else
  round_s=45; first=(3 1 3 2 1 1); each=(3 1 3 2 1 1)
  device=cpu; precision=fp32; batch=8; train_args=(--loader device --threads 1)
  [ $need_sim = 0 ] && first=(0 0 3 2 0 1) && each=(0 0 3 2 0 1)
fi

# simulate ROUND SIM_PRESSES SIM_POUCHES BASE_PRESSES BASE_POUCHES SIM_WORKERS BASE_WORKERS
simulate() {
  local k=$1 opts=(--image-size 64 --profile mixed --no-progress)
  if [ "$2" -gt 0 ]; then
    run $PY -m beadsight simulate --out "$out/sim_d$k.h5" --presses "$2" --pouches "$3" \
      --seed $((2600 + seed_offset + k)) --workers "$6" "${opts[@]}" >"$out/simulate_sim_d$k.log" 2>&1 &
  fi
  run $PY -m beadsight simulate --out "$out/base_d$k.h5" --presses "$4" --pouches "$5" \
    --variety train --looks train --seed $((2700 + seed_offset + k)) --workers "$7" "${opts[@]}" \
    >"$out/simulate_base_d$k.log" 2>&1 &
  wait
  for f in sim base; do
    [ $f = sim ] && [ "$2" -eq 0 ] && continue
    [ -f "$out/${f}_d$k.h5" ] || { log "simulate ${f}_d$k failed"; tail -5 "$out/simulate_${f}_d$k.log"; exit 1; }
  done
}

# train NAME DATA ROUND INIT BUDGET_MIN LR [EXTRA...]   (INIT "-": from scratch)
train() {
  local m=$1 data=$2 k=$3 init=$4 budget=$5 lr=$6
  shift 6
  [ "$init" = - ] || set -- --init "$init" "$@"
  run $PY -m beadsight train --data "$out/${data}_d$((k - 1)).h5" --out "$out/${m}_r$k" \
    --dropout 0 --batch-size $batch --lr "$lr" --lr-schedule cosine --split 0.95 0.05 0 \
    --seed "$k" --device $device --precision $precision --budget-min "$budget" \
    --val-every-min $val_min --checkpoint-every-min $val_min --val-stride 4 --no-progress \
    "${train_args[@]}" "$@" >"$out/train_${m}_r$k.log" 2>&1
}

log "simulating round 0 on $(nproc) cores; models: ${names[*]}"
simulate 0 "${first[@]}"
log "round 0 data ready"
declare -A ckpt
k=1
while :; do
  left=$(( deadline_s - $(elapsed) - 40 ))
  # the last round when another would not get at least half a round
  if [ $left -lt $(( round_s * 3 / 2 )) ]; then last=1; budget_s=$left; else last=0; budget_s=$round_s; fi
  [ $budget_s -lt 20 ] && { k=$((k - 1)); break; }
  budget=$(python3 -c "print(round($budget_s / 60, 3))")
  log "round $k: training for $budget min on round $((k - 1))'s presses (last: $last)"
  # each model trains on the presses of the round before while the cores simulate the next
  for m in "${models[@]}"; do
    read -r name data init lr extra <<<"$m"
    if [ -n "${ckpt[$name]:-}" ]; then  # continue the round before, its shape kept
      train "$name" "$data" $k "${ckpt[$name]}" "$budget" "$lr" ${extra:+$(grep -o -- '--color-jitter [^ ]*' <<<"$extra")} &
    else
      train "$name" "$data" $k "$init" "$budget" "$lr" $extra &
    fi
  done
  [ $last = 0 ] && simulate $k "${each[@]}" &
  wait
  rm -f "$out/sim_d$((k - 1)).h5" "$out/base_d$((k - 1)).h5"
  for name in "${names[@]}"; do
    [ -f "$out/${name}_r$k/last.pt" ] || { log "train ${name}_r$k failed"; tail -5 "$out/train_${name}_r$k.log"; exit 1; }
    log "$name round $k: $(grep 'val loss' "$out/train_${name}_r$k.log" | tail -1)"
    ckpt[$name]=$out/${name}_r$k/last.pt
  done
  if [ -n "${RESULTS:-}" ]; then
    for name in "${names[@]}"; do
      d=$out/${name}_r$k
      $PY -c "import sys, torch; c = torch.load(sys.argv[1], weights_only=True)
torch.save({k: c[k] for k in ('beadsight', 'state_dict')}, sys.argv[2])" "$d/last.pt" "$d/final.pt"
      tar cf "$RESULTS/$name.tar" -C "$d" best.pt final.pt
    done
    tar czf "$RESULTS/logs.tgz" -C "$out" --exclude='*.pt' --exclude='*.h5' .
  fi
  [ $last = 1 ] && break
  k=$((k + 1))
done
log "done after $k rounds"
