"""One training run at a given density total-variation weight, for side-by-side comparisons.

Trains DATA for MINUTES (trainer clock) with the TrainConfig defaults except
``tv_weight_density`` (72 voxels per axis at the end, as scripts/train_bundled.sh; the hold-out of
bench/train_speed.py; validation every 45 s on 8 held-out frames; seed 0; one thread) and prints
one JSON line: iterations and the validation curve. Run two at once, one per core, to compare:

    .venv/bin/python bench/tv_density.py data/vortex_tf1 0.1 3 > a.json &
    .venv/bin/python bench/tv_density.py data/vortex_tf1 0 3 > b.json

bench/results/tv_density/ holds the runs quoted in TrainConfig.tv_weight_density.
"""

import json
import sys
from pathlib import Path

from train_speed import load_split, train_once

from visnerf.config import TrainConfig
from visnerf.runtime import configure


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    data, tv, minutes = Path(argv[0]), float(argv[1]), float(argv[2])
    configure(1)
    train, val, _ = load_split(data)
    cfg = TrainConfig(iterations=10**9, time_budget_s=minutes * 60, resolution_final=72, validate_every_s=45,
                      validate_max_images=8, seed=0, tv_weight_density=tv)
    run = train_once(f"tv{tv:g}", cfg, train, val)
    print(json.dumps({"data": str(data), "tv_weight_density": tv, "minutes": minutes, "iterations": run.iterations,
                      "curve": [[round(r["train_seconds"]), r.get("val_psnr")] for r in run.curve]}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
