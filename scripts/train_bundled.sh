#!/usr/bin/env bash
# Rebuild the bundled checkpoints in checkpoints/: one scene of each slider kind (timestep
# plume_time, isovalue tangle_iso, transfer function vortex_tf1, simulation parameters cosmo_sim),
# rendered at 128x128, trained MINUTES (default 10) each on both cores with the product's recipe
# on every view, as `visnerf train DATA` does with no flags, then evaluated on its 181-frame test
# path. Checkpoints and training logs go to checkpoints/, the reports to
# bench/results/bundled_eval/NAME/; the rows of the scenes rebuilt replace theirs in
# bench/results/bundled_eval/ and the README, the others stay.
#
#   bash scripts/train_bundled.sh                    # all four
#   bash scripts/train_bundled.sh tangle_iso         # one scene
set -euo pipefail
cd "$(dirname "$0")/.."
scenes=("$@")
[ ${#scenes[@]} -eq 0 ] && scenes=(plume_time tangle_iso vortex_tf1 cosmo_sim)
.venv/bin/python bench/eval_scenes.py --scenes "${scenes[@]}" --minutes-per-scene "${MINUTES:-10}" \
  --data-root data --bundle checkpoints
