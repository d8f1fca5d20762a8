#!/usr/bin/env bash
# Trains the shipped checkpoint jaxflow/checkpoints/jaxflow_synthetic/ (configs/shipped.py, its
# round 9) and copies it in; `eval` measures it as its model card reports. Round 9 continues round 8
# (runs/shipped_r8); rounds 1-8 are one table in docs/history.md, their configs in the git history
# (git show f4f8b8e:jaxflow/configs/shipped.py, get_config("roundN")). Rerunning the train.py line
# on the same workdir resumes from its newest checkpoint.
#
#   bash scripts/train_shipped.sh              # round 9 (needs runs/shipped_r8), then the copy
#   bash scripts/train_shipped.sh copy         # only the copy of the shipped step
#   bash scripts/train_shipped.sh eval [DATA]  # the model card's tables (DATA: ../shared/data)
#   POINTS=1024 bash scripts/train_shipped.sh eval [DATA]  # the same at the training density
#   CHECKPOINT=runs/X EVAL_OUT=runs/X_eval bash scripts/train_shipped.sh eval  # another checkpoint
#   SET_PAIRS=10 ... eval       # 10 pairs of each synthetic set instead of 50 (a quick check)
#   NICE= ...                   # at normal priority (default nice -n 10)
set -euo pipefail
cd "$(dirname "$0")/.."
NICE=${NICE-nice -n 10}  # the dev box's 2 cores are shared
PY=${PYTHON:-python}  # scripts/gpu_round.sh passes its interpreter (the GPU image has python3)

if [[ "${1:-}" == "eval" ]]; then
  # evaluate.py on the shipped checkpoint (its default) at 8192 points and 32 iterations, and zero
  # flow on the same sampled pairs; JSON per set in runs/shipped_eval/, views of the real pairs.
  DATA=${2:-../shared/data}
  POINTS=${POINTS:-8192}
  OUT=${EVAL_OUT:-runs/shipped_eval$([[ $POINTS == 8192 ]] || echo "_$POINTS")}
  mkdir -p "$OUT"
  SETTINGS="--config.eval.num_points=$POINTS --config.eval.num_iters=32 --config.eval.batch_size=1"
  [[ -n "${CHECKPOINT:-}" ]] && SETTINGS+=" --checkpoint $CHECKPOINT"
  pairs=${SET_PAIRS:-50}
  SETS=("things synthetic_things:$pairs test" "lidar synthetic_lidar:$pairs test")
  for entry in "ft3d FlyingThings3D_subset_processed_35m train" "kitti KITTI_processed_occ_final test"; do
    read -r name folder split <<< "$entry"
    if [[ -d "$DATA/$folder" ]]; then SETS+=("$name $name:$DATA/$folder $split")
    else echo "no $DATA/$folder: the real $name pairs are not evaluated" >&2; fi
  done
  zero=()
  for entry in "${SETS[@]}"; do
    read -r name spec split <<< "$entry"
    zero+=("$name" "$spec" "$split")
    render=()
    [[ $name == ft3d || $name == kitti ]] && render=(--render_dir "$OUT/views_$name")
    $NICE "$PY" evaluate.py --dataset "$spec" --split "$split" $SETTINGS --json "$OUT/$name.json" \
      "${render[@]}"
  done
  # Zero flow on the same sampled pairs, every set in one process (a process start each costs more
  # than the zero flow of 50 pairs).
  $NICE "$PY" -c "
import json, sys
from jaxflow.data import open_dataset
from jaxflow.evaluation.evaluator import evaluate_zero_flow
out, points, sets = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
for name, spec, split in zip(sets[::3], sets[1::3], sets[2::3]):
  r = evaluate_zero_flow(open_dataset(spec, split=split), num_points=points, batch_size=1)
  json.dump(r, open(f'{out}/{name}_zero.json', 'w'), indent=2)
  print(spec, 'zero flow EPE', round(r['epe'], 4))
" "$OUT" "$POINTS" "${zero[@]}"
  exit 0
fi

if [[ "${1:-}" != "copy" ]]; then
  # Round 9: round 8's stage 1 continued with the window points whose flow leaves pc2's window
  # masked out of the loss (data.crop_mask_outside), a new data seed, 1400 steps.
  [[ -d runs/shipped_r8/checkpoints ]] || {
    echo "no runs/shipped_r8: round 9 continues round 8 (docs/history.md says how it was made)" >&2
    exit 1; }
  $NICE "$PY" train.py --config configs/shipped.py --workdir runs/shipped_r9
fi

# Ship the final step of round 9's stage 1 (parameters, config and optimiser state; its refinement
# parameters are untrained and unused: a stage-1 checkpoint gives the coarse flow).
SHIP=runs/shipped_r9
STEP=$(ls $SHIP/checkpoints | grep -E '^[0-9]+$' | sort -n | tail -1)
DEST=jaxflow/checkpoints/jaxflow_synthetic
mkdir -p "$DEST"
find "$DEST" -mindepth 1 -maxdepth 1 -name '[0-9]*' -type d -exec rm -rf {} +
cp -r "$SHIP/checkpoints/$STEP" "$DEST/$STEP"
cp $SHIP/config.json "$DEST/config.json"
# One learning curve for the rounds: each run's steps (training and held-out metrics) are counted on
# from where the previous run ended; the end-of-run evaluation is the last run's.
"$PY" - "$DEST/learning_curve.png" runs/shipped_r2_warmup runs/shipped_r2 runs/shipped_r3 \
  runs/shipped_r4 runs/shipped_r5 runs/shipped_r6 runs/shipped_r7 runs/shipped_r8 runs/shipped_r9 \
  <<'PY'
import json, pathlib, shutil, sys
from jaxflow import viz
joined = pathlib.Path("runs/shipped_rounds")
joined.mkdir(exist_ok=True)
lines, offset = {"metrics.jsonl": [], "eval_metrics.jsonl": []}, 0
for run in [r for r in sys.argv[2:] if pathlib.Path(r, "metrics.jsonl").exists()]:
  for name, out in lines.items():
    path = pathlib.Path(run, name)
    records = [json.loads(l) for l in path.read_text().splitlines() if l] if path.exists() else []
    out += [json.dumps({**r, "step": r["step"] + offset}) + "\n" for r in records]
  offset = json.loads(lines["metrics.jsonl"][-1])["step"]  # where this run ended, joined
for name, out in lines.items():
  (joined / name).write_text("".join(out))
shutil.copy(pathlib.Path(sys.argv[-1], "eval.json"), joined / "eval.json")
viz.plot_learning_curves(joined / "metrics.jsonl", sys.argv[1])
PY
du -sh "$DEST"
