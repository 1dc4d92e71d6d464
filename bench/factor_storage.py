"""What a coarser storage of the VM factors (``FieldConfig.factor_storage``) does to the frames: a
checkpoint renders its held-out frames as stored and as a checkpoint with ``--storage`` (float16,
or int8 planes with row scales) would hold them, saved and loaded back through the checkpoint code.

    .venv/bin/python bench/factor_storage.py CKPT --data ../shared/data/nyx --storage int8 \\
        --holdout-views 5,17,29,40 --holdout-params "0.12,0.0235,0.625;0.1375,0.0215,0.775"

Writes bench/results/factor_storage.md and .json (float16), factor_storage_int8.md and .json (int8).
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
PRECISION = {"float32": 2, "float16": 1, "int8": 0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint", help="a checkpoint whose factors are stored finer than --storage")
    ap.add_argument("--storage", choices=("float16", "int8"), default="float16")
    ap.add_argument("--data", required=True)
    ap.add_argument("--holdout-views", type=parse_views, default=())
    ap.add_argument("--holdout-params", type=parse_settings, default=())
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--results", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    field, meta = load_checkpoint(args.checkpoint, torch.device("cpu"))
    if PRECISION[meta.field.factor_storage] <= PRECISION[args.storage]:
        print(f"error: {args.checkpoint} stores its factors as {meta.field.factor_storage}, no finer than "
              f"--storage {args.storage}", file=sys.stderr)
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
    # Round through the checkpoint code itself: save with the coarser factors, load back.
    field.cfg = dataclasses.replace(meta.field, factor_storage=args.storage)
    with tempfile.TemporaryDirectory() as tmp:
        coarse_path = save_checkpoint(field, dataclasses.replace(meta, field=field.cfg), Path(tmp) / "coarse.safetensors")
        coarse, _ = load_checkpoint(coarse_path, torch.device("cpu"))
        sizes = (Path(args.checkpoint).stat().st_size, coarse_path.stat().st_size)
    rounded = frames(coarse)
    old, new = meta.field.factor_storage, args.storage
    result = {
        "command": "python bench/factor_storage.py " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "frames": len(idx),
        "resolution": list(field.resolution),
        "stored_as": old,
        "coded_as": new,
        "file_mb": [round(s / 1e6, 3) for s in sizes],
        f"psnr_{old}": float(np.mean([psnr(a, t) for a, t in zip(stored, truth, strict=True)])),
        f"psnr_{new}": float(np.mean([psnr(b, t) for b, t in zip(rounded, truth, strict=True)])),
        f"{new}_against_{old}_db": float(np.mean([psnr(b, a) for a, b in zip(stored, rounded, strict=True)])),
        "max_abs_difference": float(max(np.abs(a - b).max() for a, b in zip(stored, rounded, strict=True))),
    }
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    stem = "factor_storage" if new == "float16" else f"factor_storage_{new}"
    write_json(out / f"{stem}.json", result)
    lines = [f"# {new} factors in the checkpoint", "", f"Command: `{result['command']}`  ", f"Date: {result['date']}", "",
             f"| frames | grid | file MB, {old} / {new} | PSNR against ground truth, {old} factors | {new} factors | "
             f"{new} frames against {old} frames | largest channel difference |",
             "| --- | --- | --- | --- | --- | --- | --- |",
             f"| {result['frames']} | {result['resolution']} | {result['file_mb'][0]} / {result['file_mb'][1]} | "
             f"{result[f'psnr_{old}']:.4f} dB | {result[f'psnr_{new}']:.4f} dB | "
             f"{result[f'{new}_against_{old}_db']:.1f} dB | {result['max_abs_difference']:.4f} |", ""]
    (out / f"{stem}.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
