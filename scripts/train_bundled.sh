#!/usr/bin/env bash
# Rebuild the bundled checkpoints in checkpoints/ from the synthetic scenes, with the recorded
# settings. Each scene is rendered at 128x128 (data/<scene>/), trained for MINUTES of wall time
# (default: 8 for vortex_tf1; 15 for tangle_iso, whose opaque surfaces put more samples on every
# ray) on THREADS torch threads (default 1), and written with its training log.
#
#   bash scripts/train_bundled.sh            # both scenes
#   bash scripts/train_bundled.sh tangle_iso # one scene
set -euo pipefail
cd "$(dirname "$0")/.."
export VISNERF_THREADS="${THREADS:-1}"
# 72 voxels per axis keeps a checkpoint under 5 MB (3 planes x 64 components x 72^2 floats = 4 MB
# in a cube; boxes that are not cubes have larger planes for the same voxel count).
RESOLUTION="${RESOLUTION:-72}"
scenes=("$@")
[ ${#scenes[@]} -eq 0 ] && scenes=(tangle_iso vortex_tf1)
for scene in "${scenes[@]}"; do
  data="data/${scene}"
  if [ ! -f "${data}/transforms_train.json" ]; then
    .venv/bin/visnerf make-scene "${scene}" --out "${data}" --res 128 --quiet --force
  fi
  minutes="${MINUTES:-8}"
  [ "${scene}" = tangle_iso ] && minutes="${MINUTES:-15}"
  .venv/bin/visnerf train "${data}" --out "checkpoints/${scene}.safetensors" --force --quiet \
    --time-budget "${minutes}" --resolution "${RESOLUTION}" --holdout-views 5,17,29,40 \
    --validate-every 60 --seed 0
done
