#!/usr/bin/env bash
# The main job: set up, build the redkitchen demo bag, start register_node with config/genreg.yaml, replay
# the bag through it at its original 30 Hz timing and print the summary (pairs, RE/TE, latency, drops).
# Usage: bash scripts/main_job.sh      (needs ../shared/data beside the checkout, or GENREG_DATA)
# Env: GENREG_MODEL (checkpoint name or path; default: model.checkpoint of config/genreg.yaml),
#      ROS_DOMAIN_ID (default: a random one in 101..199, so parallel runs never meet).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 99) + 101 ))}
export FASTDDS_DEFAULT_PROFILES_FILE=${FASTDDS_DEFAULT_PROFILES_FILE:-$PWD/config/fastdds_large_clouds.xml}

BAG=cache/bags/redkitchen_demo   # generated on demand, never committed (cache/ is ignored)
REPORT=cache/replay/main_job
START=$(date +%s)

# Demo bag: 100 frames of the validation part (800-999) of 7-Scenes redkitchen seq-01, colour, 30 Hz.
if [ ! -f "$BAG/metadata.yaml" ]; then
  python -m genreg_ros.bag.make_bag --sequence redkitchen --start 800 --count 100 --pixel-stride 4 \
    --out "$BAG" --overwrite
else
  echo "demo bag: $BAG (exists)"
fi

# Model: GENREG_MODEL if set, else the shipped scene model (genreg_core/weights/7scenes.pt) if present, else
# the node's default (model.checkpoint in config/genreg.yaml). A missing checkpoint is a one-line error.
if [ -n "${GENREG_MODEL:-}" ]; then
  MODEL=$GENREG_MODEL
elif [ -f genreg_core/weights/7scenes.pt ]; then
  MODEL=7scenes
else
  MODEL=$(python -c "from genreg_ros.replay.harness import yaml_param; \
from genreg_core.config import OBJECT_MODEL; \
print(yaml_param('config/genreg.yaml', 'model.checkpoint', OBJECT_MODEL))")
fi
echo "model: $MODEL    ROS_DOMAIN_ID=$ROS_DOMAIN_ID    report: $REPORT/report.md"

python -m genreg_ros.replay --bag "$BAG" --gap 1 --rate 1.0 --checkpoint "$MODEL" --report "$REPORT"
echo "main job done in $(( $(date +%s) - START )) s after setup"
