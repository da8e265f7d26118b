#!/usr/bin/env bash
# Backbone ablation: train two GenReg object models that differ only in the backbone
# (pointmixer = the shipped `modelnet40` architecture, dgcnn = without the mixer layers, as the shipped
# `modelnet40_dgcnn`), same recipe (config/train_modelnet40_ppf.yaml), seed and budget, then compare them
# with `genreg-bench --ablation backbone`. Resumable: re-running continues each run from its checkpoint.
#   bash scripts/ablation_backbone.sh [STEPS=600] [PAIRS=100]
# Cost on 2 cores: two runs side by side, 1 thread each. Without training, `genreg-bench --ablation
# backbone` compares the two shipped models (add --paper-checkpoint PATH for the paper's generator).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-600}
PAIRS=${2:-100}
. .venv/bin/activate
mkdir -p runs
export OMP_WAIT_POLICY=PASSIVE
for name in pointmixer dgcnn; do
  genreg-train --config config/train_modelnet40_ppf.yaml --resume --no-progress \
    --set threads=1 "out_dir=runs/abl_$name" "model.backbone=$name" "schedule.steps=$STEPS" validate_every=300 \
    > "runs/abl_$name.log" 2>&1 &
done
wait
genreg-bench --suite full --ablation backbone --datasets modelnet-unseen-clean modelnet-unseen-partial --object-points 512 \
  --backbones pointmixer=runs/abl_pointmixer/last.pt dgcnn=runs/abl_dgcnn/last.pt --max-pairs "$PAIRS" --seed 0 --threads 2 --out build/ablation_backbone
