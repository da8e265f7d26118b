#!/usr/bin/env bash
# Backbone ablation (issue 5): train three GenReg object models that differ only in the encoder backbone
# (pointmixer = shipped architecture, dgcnn = without the mixer layers, pointnet2 = PointNet++-style),
# same recipe (config/train_modelnet40_ppf.yaml), seed and budget, then compare them with
# `genreg-bench --ablation backbone`. Resumable: re-running continues each run from its checkpoint.
#   bash scripts/ablation_backbone.sh [STEPS=600] [PAIRS=100]
# Cost on 2 cores: three runs side by side, 1 thread each, ~3.5 s per iteration -> ~35 min at 600 steps.
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-600}
PAIRS=${2:-100}
. .venv/bin/activate
mkdir -p runs
export OMP_WAIT_POLICY=PASSIVE
for name in pointmixer dgcnn pointnet2; do
  genreg-train --config config/train_modelnet40_ppf.yaml --resume --no-progress \
    --set threads=1 "out_dir=runs/abl_$name" "model.backbone=$name" "schedule.steps=$STEPS" validate_every=300 \
    > "runs/abl_$name.log" 2>&1 &
done
wait
genreg-bench --suite full --ablation backbone --datasets modelnet-unseen-clean modelnet-unseen-partial --object-points 512 \
  --max-pairs "$PAIRS" --seed 0 --threads 2 --out build/ablation_backbone
