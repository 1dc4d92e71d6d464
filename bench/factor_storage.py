"""What storing the VM factors as float16 (``FieldConfig.factor_storage``) does to the frames: a
checkpoint whose factors are float32 renders its held-out frames as stored and with the factors
rounded to float16, as a float16 checkpoint would hold them.

    .venv/bin/python bench/factor_storage.py CKPT --data ../shared/data/nyx \\
        --holdout-views 5,17,29,40 --holdout-params "0.12,0.0235,0.625;0.1375,0.0215,0.775"

Writes bench/results/factor_storage.md and .json.
"""

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_common import write_json

from visnerf.checkpoint import load_checkpoint, save_checkpoint
from visnerf.commands import parse_settings, parse_views
from visnerf.config import HoldoutConfig
from visnerf.data.holdout import split_holdout
from visnerf.data.parsers.blender import load_dataset
from visnerf.evaluation.metrics import psnr
from visnerf.rendering.renderer import RenderSettings, render_image

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="a checkpoint with float32 factors")
    ap.add_argument("--data", required=True)
    ap.add_argument("--holdout-views", type=parse_views, default=())
    ap.add_argument("--holdout-params", type=parse_settings, default=())
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--results", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    field, meta = load_checkpoint(args.checkpoint, torch.device("cpu"))
    if meta.field.factor_storage != "float32":
        print(f"error: {args.checkpoint} stores its factors as {meta.field.factor_storage}; this needs float32",
              file=sys.stderr)
        return 2
    _, val = split_holdout(load_dataset(args.data), HoldoutConfig(views=args.holdout_views,
                                                                  settings=args.holdout_params))
    if val is None:
        print("error: the hold-out options select no frame", file=sys.stderr)
        return 2
    settings = RenderSettings.from_meta(meta)
    params = val.normalized_params()
    idx = np.unique(np.linspace(0, val.n_frames - 1, args.frames).round().astype(int))
    truth = [val.images[i].numpy().astype(np.float32) / 255.0 for i in idx]

    def frames(model: torch.nn.Module) -> list[np.ndarray]:
        with torch.inference_mode():
            return [render_image(model, val.c2w[i], val.intrinsics, params[i], settings).clamp(0, 1).numpy()
                    for i in idx]

    stored = frames(field)
    # Round through the checkpoint code itself: save with float16 factors, load back.
    field.cfg = dataclasses.replace(meta.field, factor_storage="float16")
    with tempfile.TemporaryDirectory() as tmp:
        half_path = save_checkpoint(field, dataclasses.replace(meta, field=field.cfg), Path(tmp) / "half.safetensors")
        half, _ = load_checkpoint(half_path, torch.device("cpu"))
    rounded = frames(half)
    result = {
        "command": "python bench/factor_storage.py " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "frames": len(idx),
        "resolution": list(field.resolution),
        "psnr_float32": float(np.mean([psnr(a, t) for a, t in zip(stored, truth, strict=True)])),
        "psnr_float16": float(np.mean([psnr(b, t) for b, t in zip(rounded, truth, strict=True)])),
        "float16_against_float32_db": float(np.mean([psnr(b, a) for a, b in zip(stored, rounded, strict=True)])),
        "max_abs_difference": float(max(np.abs(a - b).max() for a, b in zip(stored, rounded, strict=True))),
    }
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "factor_storage.json", result)
    lines = ["# Float16 factors in the checkpoint", "", f"Command: `{result['command']}`  ", f"Date: {result['date']}", "",
             "| frames | grid | PSNR against ground truth, float32 factors | float16 factors | float16 frames against float32 frames | largest channel difference |",
             "| --- | --- | --- | --- | --- | --- |",
             f"| {result['frames']} | {result['resolution']} | {result['psnr_float32']:.4f} dB | {result['psnr_float16']:.4f} dB | "
             f"{result['float16_against_float32_db']:.1f} dB | {result['max_abs_difference']:.4f} |", ""]
    (out / "factor_storage.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
