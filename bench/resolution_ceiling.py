"""How much detail a dataset's images hold at the pixel scale: each image is downsampled by a
factor (area average) and upsampled back (bilinear), and compared with itself: an indication of
how much of the images' detail lies at the scale of ``factor`` pixels, where a model whose voxels
project to that many pixels has trouble holding it. Not a bound: a model renders, it does not
upsample.

    .venv/bin/python bench/resolution_ceiling.py                 # shared/data/nyx
    .venv/bin/python bench/resolution_ceiling.py --data data/vortex_tf1

Writes bench/results/resolution_ceiling.md and .json (one entry per dataset name).
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from bench_common import write_json

from visnerf.data.parsers.blender import load_dataset
from visnerf.evaluation.metrics import psnr

ROOT = Path(__file__).resolve().parents[1]
FACTORS = (1.25, 1.5, 2.0, 3.0)


def round_trip(image: torch.Tensor, factor: float) -> torch.Tensor:
    """``image`` [h, w, 3] in [0, 1], area-downsampled by ``factor`` and bilinearly upsampled back."""
    h, w = image.shape[:2]
    x = image.permute(2, 0, 1)[None]
    small = F.interpolate(x, size=(max(1, round(h / factor)), max(1, round(w / factor))), mode="area")
    return F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "nyx"))
    ap.add_argument("--images", type=int, default=24, help="images, evenly chosen (default 24)")
    ap.add_argument("--results", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()
    scene = load_dataset(args.data)
    idx = np.unique(np.linspace(0, scene.n_frames - 1, args.images).round().astype(int))
    rows = {}
    for factor in FACTORS:
        values = []
        for i in idx:
            image = scene.images[i].float() / 255.0
            values.append(psnr(round_trip(image, factor).clamp(0, 1).numpy(), image.numpy()))
        rows[str(factor)] = {"mean_psnr": float(np.mean(values)), "min": float(np.min(values)),
                             "max": float(np.max(values))}
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    store = out / "resolution_ceiling.json"
    everything = json.loads(store.read_text()) if store.exists() else {}
    name = Path(args.data).name
    everything[name] = {"images": len(idx), "size": [scene.intrinsics.width, scene.intrinsics.height], "factors": rows}
    write_json(store, everything)
    lines = ["# Detail at the pixel scale", "",
             "Each image area-downsampled by the factor and bilinearly upsampled back, PSNR against itself "
             "(`python bench/resolution_ceiling.py --data DATA`). How much of the images' detail lies at that "
             "scale: a crude indication for a model whose voxels project to that many pixels, not a bound (a model "
             "renders, it does not upsample).", "",
             "| dataset | images | " + " | ".join(f"x{f:g}" for f in FACTORS) + " |",
             "| --- | --- | " + " | ".join("---" for _ in FACTORS) + " |"]
    for key, entry in sorted(everything.items()):
        cells = " | ".join(f"{entry['factors'][str(f)]['mean_psnr']:.2f} dB" for f in FACTORS)
        lines.append(f"| {key} ({entry['size'][0]}x{entry['size'][1]}) | {entry['images']} | {cells} |")
    (out / "resolution_ceiling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
