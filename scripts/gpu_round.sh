#!/usr/bin/env bash
# A training round of the shipped checkpoint on a lent GPU (configs/gpu_round.py), in device calls of
# under 10 minutes each, from the repository root there. What a call reports lands in $OUT (the
# device tool's folder; runs/gpu_out when unset), packed so that it comes back (at most 8 files).
#
#   bash scripts/gpu_round.sh bench             # the network's table against the official
#                                               # PV-RAFT's (benchmarks.network_gpu), the
#                                               # selections (benchmarks.selection): ~4 minutes
#   bash scripts/gpu_round.sh device            # the GPU round, one call of < 10 minutes: the
#                                               # GPU-marked tests, model_speed at both precisions
#                                               # and with --deterministic's flag, the methods
#                                               # benchmark, device-vs-host nearest search
#   DRY=1 ...device                             # the same steps at toy sizes (on the CPU too)
#     (device: here `python3 -m pip download --no-deps -d .whl ml_collections==1.1.0`, then the
#     device tool's run with command "bash scripts/gpu_round.sh device", carry [".whl"],
#     timeout_s 600; results into benchmarks/ with the device: SEARCH.md, MODEL.md, METHODS.md)
#   bash scripts/gpu_round.sh train MINUTES [--config.FIELD=VALUE ...]  # (resume and) train, pack
#   bash scripts/gpu_round.sh eval [DATA]       # deciding pairs (synthetic_mix:100 val) for the
#                                               # round and the shipped checkpoint, then the model
#                                               # card's protocol sets (DATA: real samples)
#   POINTS=N ...eval                            # at N points instead of the protocol's 8192
#   DECIDE=SPEC ...eval                         # other deciding pairs (a synthetic_mix:COUNT)
#
# Carry `.whl` (the ml_collections wheel, which the GPU image lacks) and, for eval, DATA (e.g. a copy
# of ../shared/data in an ignored folder). The run lives in runs/gpu_round, which stays between
# calls while the machine is warm; on a fresh machine a carried .gpu_carry/gpu_round.tgz (a
# previous call's pack; CARRY names another) is unpacked first, so the round resumes where that
# call stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-runs/gpu_out}
WORK=${WORK:-runs/gpu_round}  # the round's workdir (the tests point it elsewhere)
CARRY=${CARRY:-.gpu_carry/gpu_round.tgz}
PY=${PYTHON:-python3}
EVAL=${EVAL:-runs/gpu_round_eval}  # where eval writes (the tests point it elsewhere)
mkdir -p "$OUT" "$(dirname "$WORK")"
export PYTHONUNBUFFERED=1
if ! "$PY" -c "import ml_collections" 2>/dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
if [[ ! -d $WORK && -f $CARRY ]]; then
  mkdir -p "$WORK"
  tar -xzf "$CARRY" -C "$WORK"
fi

case "${1:-}" in
  bench)
    # The network's table (benchmarks/NETWORK_GPU.md) and the selections, in a few minutes.
    if [[ -n ${DRY:-} ]]; then  # toy sizes: checks the commands, measures nothing
      net=(--points 256 --iters 2 --train_iters 1 --repeats 1) sel=(--points 1024 --repeats 1)
    else
      net=() sel=()
    fi
    { nvidia-smi -L || true
      "$PY" -m benchmarks.network_gpu "${net[@]}" --set remat_iterations=true
      "$PY" -m benchmarks.selection "${sel[@]}"
    } 2>&1 | tee "$OUT/bench.txt"
    ;;
  device)
    # Each step has its own time limit and the whole stays under DEADLINE seconds: a step that
    # fails or runs out is logged and the next one runs. Back in $OUT: device_round.txt (every
    # step's output), methods.json, search.json; copy them into benchmarks/ with the device.
    start=$SECONDS
    deadline=${DEADLINE:-560}  # seconds: the device call's 600 less the install
    log="$OUT/device_round.txt"
    : >"$log"
    steps=0  # MAX_STEPS=N runs the first N steps only (the tests: no dependence on speed)
    step() {  # step NAME SECONDS COMMAND...
      local name=$1 limit=$2 left=$((deadline - (SECONDS - start))) rc=0
      shift 2
      steps=$((steps + 1))
      if [[ -n ${MAX_STEPS:-} ]] && ((steps > MAX_STEPS)); then
        echo "== $name: skipped (MAX_STEPS=$MAX_STEPS)" | tee -a "$log"
        return 0
      fi
      ((left < limit)) && limit=$left
      if ((limit < 10)); then
        echo "== $name: skipped (the round's ${deadline} s are spent)" | tee -a "$log"
        return 0
      fi
      echo "== $name (limit ${limit} s): $*" | tee -a "$log"
      timeout -s KILL "$limit" "$@" 2>&1 | tee -a "$log" || rc=$?
      echo "== $name: exit $rc after $((SECONDS - start)) s in all" | tee -a "$log"
    }
    if [[ -n ${DRY:-} ]]; then  # toy sizes: checks the steps, measures nothing
      points=256 sizes=512 iters=2 methods_args=(--synthetic 1 --num-points 256 --nsfp-steps 3)
      speed_configs=default_cpu repeats=1
    else
      points=8192 sizes=8192,100000 iters=32 methods_args=(--synthetic 2 --nsfp-steps 1000)
      speed_configs=default_full,pvraft repeats=3
    fi
    # In the order of the issue's asks: what does not fit in the deadline is what matters least.
    step devices 20 bash -c "nvidia-smi -L || true; $PY -c 'import jax; print(jax.devices())'"
    step gpu_tests 100 "$PY" -m pytest -q -n 0 -m gpu -rA tests/test_gpu.py
    for precision in highest default; do
      step "model_speed_$precision" 90 "$PY" -m benchmarks.model_speed --points "$points" \
        --iters "$iters" --configs "$speed_configs" --precision "$precision" --repeats "$repeats"
    done
    step methods 150 "$PY" benchmarks/methods.py "${methods_args[@]}" --json "$OUT/methods.json"
    step search 45 "$PY" -m benchmarks.search --sizes "$sizes" --repeats "$repeats" \
      --json "$OUT/search.json"
    # The cost of --deterministic: a training step with and without XLA's deterministic ops.
    for flags in "" "--xla_gpu_deterministic_ops=true"; do
      step "train_step_xla_flags=${flags:-none}" 60 env XLA_FLAGS="$flags" "$PY" -m \
        benchmarks.model_speed --points "$points" --iters 8 --configs default_cpu --train \
        --repeats "$repeats"
    done
    echo "device round: $((SECONDS - start)) s" | tee -a "$log"
    ;;
  train)
    minutes=${2:?"train needs MINUTES"}
    shift 2
    # SIGTERM at the deadline: train.py saves the step it is at and exits (124 from timeout).
    rc=0
    timeout -s TERM "${minutes}m" "$PY" train.py --config configs/gpu_round.py --workdir "$WORK" \
      "$@" 2>&1 | tee "$OUT/train.log" || rc=$?
    [[ $rc == 0 || $rc == 124 ]] || { echo "train.py failed (exit $rc)" >&2; exit "$rc"; }
    if ! ls "$WORK/checkpoints" 2>/dev/null | grep -qE '^[0-9]+$'; then
      echo "no checkpoint in $WORK: stopped before training began; give more than $minutes minutes" >&2
      exit 1
    fi
    tar -czf "$OUT/gpu_round.tgz" -C "$WORK" .
    tail -n 3 "$WORK/metrics.jsonl"
    ;;
  eval)
    DATA=${2:-.gpu_data}
    mkdir -p "$EVAL"
    # The round replaces the shipped checkpoint only if better on these validation pairs. Rounds
    # 8-9 showed that 16 pairs are too few (MODEL_CARD.md): 100 here, both measured on this device.
    decide=${DECIDE:-synthetic_mix:100}
    for who in round shipped; do
      checkpoint=()
      [[ $who == round ]] && checkpoint=(--checkpoint "$WORK")
      "$PY" evaluate.py "${checkpoint[@]}" --dataset "$decide" --split val \
        --config.eval.batch_size=2 --config.eval.num_points="${POINTS:-8192}" \
        --json "$EVAL/decide_val_$who.json"
    done
    CHECKPOINT="$WORK" EVAL_OUT="$EVAL" PYTHON="$PY" bash scripts/train_shipped.sh eval "$DATA"
    tar -czf "$OUT/gpu_round_eval.tgz" -C "$(dirname "$EVAL")" "$(basename "$EVAL")"
    "$PY" - "$EVAL" <<'PY'
import json, pathlib, sys
for path in sorted(pathlib.Path(sys.argv[1]).glob("*.json")):
  print(f"{path.stem:>14}: EPE {json.loads(path.read_text())['epe']:.4f} m")
PY
    ;;
  *)
    echo "usage: bash scripts/gpu_round.sh bench | device | train MINUTES [FLAGS] | eval [DATA]" >&2
    exit 2
    ;;
esac
