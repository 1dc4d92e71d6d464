"""One training run at a given training sample spacing, for side-by-side comparisons.

Trains DATA for MINUTES (trainer clock) with the TrainConfig defaults and samples STEP_RATIO
voxels apart (``RenderConfig.step_ratio``; 72 voxels per axis at the end, as
scripts/train_bundled.sh; the hold-out of bench/train_speed.py; validation every 45 s on 8
held-out frames; seed 0; one thread) and prints one JSON line: iterations, the validation curve,
and the full-quality spacing chosen at the end (the last validation renders at it). Run two at
once, one per core, to compare:

    .venv/bin/python bench/train_step_ratio.py data/vortex_tf1 0.5 3 > a.json &
    .venv/bin/python bench/train_step_ratio.py data/vortex_tf1 1.0 3 > b.json

bench/results/train_step_ratio/ holds the runs quoted in RenderConfig.step_ratio.
"""

import json
import sys
from pathlib import Path

from train_speed import load_split, train_once

from visnerf.config import RenderConfig, TrainConfig
from visnerf.runtime import configure


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    data, step_ratio, minutes = Path(argv[0]), float(argv[1]), float(argv[2])
    if not step_ratio > 0.0 or not minutes > 0.0:
        print(f"STEP_RATIO and MINUTES must be positive, got {step_ratio} and {minutes}", file=sys.stderr)
        return 2
    configure(1)
    train, val, _ = load_split(data)
    cfg = TrainConfig(iterations=10**9, time_budget_s=minutes * 60, resolution_final=72, validate_every_s=45,
                      validate_max_images=8, seed=0)
    run = train_once(f"step{step_ratio:g}", cfg, train, val, RenderConfig(step_ratio=step_ratio))
    print(json.dumps({"data": str(data), "step_ratio": step_ratio, "minutes": minutes, "iterations": run.iterations,
                      "full_step_ratio": run.full_step_ratio, "curve": [[round(r["train_seconds"]), r.get("val_psnr")] for r in run.curve]}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
