#!/usr/bin/env bash
# Trains the shipped checkpoint checkpoints/jaxflow_synthetic/ (configs/shipped.py) and copies it in.
# Each round is the exact command that was run; rerunning a train.py line on the same workdir resumes
# from its newest checkpoint (a later round may raise --config.train.num_steps). See MODEL_CARD.md.
#
#   bash scripts/train_shipped.sh            # all rounds, then the copy
#   bash scripts/train_shipped.sh copy       # only the copy of the final stage-2 step
#   bash scripts/train_shipped.sh eval [DATA]  # the model card's tables (DATA: ../shared/data)
#   POINTS=1024 bash scripts/train_shipped.sh eval [DATA]  # the same at the training density
set -euo pipefail
cd "$(dirname "$0")/.."
NICE="nice -n 10"  # the dev box's 2 cores are shared

if [[ "${1:-}" == "eval" ]]; then
  # evaluate.py on the shipped checkpoint (its default) at 8192 points and 32 iterations, and zero
  # flow on the same sampled pairs; JSON per set in runs/shipped_eval/, views of the real pairs.
  DATA=${2:-../shared/data}
  POINTS=${POINTS:-8192}
  OUT=runs/shipped_eval$([[ $POINTS == 8192 ]] || echo "_$POINTS")
  mkdir -p "$OUT"
  SETTINGS="--config.eval.num_points=$POINTS --config.eval.num_iters=32 --config.eval.batch_size=1"
  SETS=("things synthetic_things:50 test" "lidar synthetic_lidar:50 test")
  [[ -d "$DATA/FlyingThings3D_subset_processed_35m" ]] && \
    SETS+=("ft3d ft3d:$DATA/FlyingThings3D_subset_processed_35m train")
  [[ -d "$DATA/KITTI_processed_occ_final" ]] && SETS+=("kitti kitti:$DATA/KITTI_processed_occ_final test")
  for entry in "${SETS[@]}"; do
    read -r name spec split <<< "$entry"
    render=()
    [[ $name == ft3d || $name == kitti ]] && render=(--render "$OUT/views_$name")
    $NICE python evaluate.py --dataset "$spec" --split "$split" $SETTINGS --json "$OUT/$name.json" \
      "${render[@]}"
    $NICE python -c "
import json, sys
from jaxflow.data import open_dataset
from jaxflow.evaluation import evaluate_zero_flow
r = evaluate_zero_flow(open_dataset(sys.argv[1], split=sys.argv[2]), num_points=int(sys.argv[4]),
                       batch_size=1)
json.dump(r, open(sys.argv[3], 'w'), indent=2)
print(sys.argv[1], 'zero flow EPE', round(r['epe'], 4))
" "$spec" "$split" "$OUT/${name}_zero.json" "$POINTS"
  done
  exit 0
fi

if [[ "${1:-}" != "copy" ]]; then
  # Stage 1, round 1: 600 steps of 2 pairs x 1024 points on synthetic_mix.
  $NICE python train.py --config configs/shipped.py --workdir runs/shipped
  # Stage 2: the graph refinement on the frozen round-1 network, 150 steps.
  $NICE python train.py --config configs/shipped.py:stage2 --workdir runs/shipped_stage2 \
    --config.train.init_from=runs/shipped
fi

# Ship only the final stage-2 step: it holds every parameter (the frozen backbone too), the config and
# the optimiser state of the refinement alone (stage 2's frozen group keeps none).
STEP=$(ls runs/shipped_stage2/checkpoints | grep -E '^[0-9]+$' | sort -n | tail -1)
DEST=checkpoints/jaxflow_synthetic
mkdir -p "$DEST"
find "$DEST" -mindepth 1 -maxdepth 1 -name '[0-9]*' -type d -exec rm -rf {} +
cp -r "runs/shipped_stage2/checkpoints/$STEP" "$DEST/$STEP"
cp runs/shipped_stage2/config.json "$DEST/config.json"
cat runs/shipped/metrics.jsonl runs/shipped_stage2/metrics.jsonl > runs/shipped_stage2/both_stages.jsonl
python -c "from jaxflow import viz; viz.plot_learning_curves(
  'runs/shipped_stage2/both_stages.jsonl', '$DEST/learning_curve.png')"
du -sh "$DEST"
