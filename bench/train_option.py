"""One short training run with one option changed, for side-by-side comparisons.

    .venv/bin/python bench/train_option.py DATA OPTION VALUE MINUTES

Trains DATA for MINUTES (trainer clock) with the defaults except OPTION (72 voxels per axis at
the end, as scripts/train_bundled.sh; the hold-out of bench/train_speed.py; validation every 45 s
on 8 held-out frames; seed 0; one thread) and prints one JSON line: iterations, the validation
curve, and the full-quality spacing the run chose at its end (its last validation renders at it).
OPTION is one of:

- ``tv_density``: ``TrainConfig.tv_weight_density`` (bench/results/tv_density/);
- ``step_ratio``: the training sample spacing in voxels, ``RenderConfig.step_ratio``
  (bench/results/train_step_ratio/).

Run two at once, one per core, to compare:

    .venv/bin/python bench/train_option.py data/vortex_tf1 step_ratio 0.5 3 > a.json &
    .venv/bin/python bench/train_option.py data/vortex_tf1 step_ratio 1.0 3 > b.json
"""

import json
import math
import sys
from pathlib import Path

from train_speed import load_split, train_once

from visnerf.config import RenderConfig, TrainConfig
from visnerf.runtime import configure

OPTIONS = ("tv_density", "step_ratio")


def main(argv: list[str]) -> int:
    if len(argv) != 4 or argv[1] not in OPTIONS:
        print(__doc__, file=sys.stderr)
        return 2
    data, option = Path(argv[0]), argv[1]
    try:
        value, minutes = float(argv[2]), float(argv[3])
    except ValueError:
        print(f"VALUE and MINUTES must be numbers, got {argv[2]!r} and {argv[3]!r}", file=sys.stderr)
        return 2
    if not (math.isfinite(value) and value >= 0.0 and minutes > 0.0) or (option == "step_ratio" and value <= 0.0):
        print(f"{option} must be {'positive' if option == 'step_ratio' else 'at least 0'} and MINUTES positive, "
              f"got {value} and {minutes}", file=sys.stderr)
        return 2
    configure(1)
    train, val, _ = load_split(data)
    cfg = TrainConfig(iterations=10**9, time_budget_s=minutes * 60, resolution_final=72, validate_every_s=45,
                      validate_max_images=8, seed=0,
                      **({"tv_weight_density": value} if option == "tv_density" else {}))
    render = RenderConfig(step_ratio=value) if option == "step_ratio" else RenderConfig()
    run = train_once(f"{option}{value:g}", cfg, train, val, render)
    print(json.dumps({"data": str(data), option: value, "minutes": minutes, "iterations": run.iterations,
                      "full_step_ratio": run.full_step_ratio,
                      "curve": [[round(r["train_seconds"]), r.get("val_psnr")] for r in run.curve]}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
