"""A contact sheet of generated datasets: a few training and test views of each, one row per scene.

``python -m visnerf.scenes.contact_sheet DIR [DIR ...] --out sheet.png``
"""

import argparse
import json
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont


def _pick(count: int, n: int, margin: float) -> list[int]:
    """``n`` indices spread evenly over ``range(count)`` (repeating when ``count < n``), keeping
    ``margin`` (a fraction of the range) off both ends."""
    span = (1.0 - 2.0 * margin) * (count - 1)
    return [round(margin * (count - 1) + i * span / max(n - 1, 1)) for i in range(n)]


def _caption(frame: dict, split: str) -> str:
    params = ", ".join(f"{p:.3g}" for p in frame.get("params", []))
    return f"{split} {params}" if params else split


def _dataset_tiles(dataset: Path, n_train: int, n_test: int, tile: int) -> tuple[dict, list]:
    train = json.loads((dataset / "transforms_train.json").read_text())
    test_path = dataset / "transforms_test.json"
    test = json.loads(test_path.read_text()) if test_path.exists() else {"frames": []}
    frames = train["frames"]
    n_settings = max(1, len({tuple(f.get("params", [])) for f in frames}))
    n_views = max(1, len(frames) // n_settings)
    # view-major frames (r = view * n_settings + setting): vary both the view and the setting
    picks = [
        frames[v * n_settings + s]
        for v, s in zip(_pick(n_views, n_train, 0.1), _pick(n_settings, n_train, 0.0), strict=False)
    ]
    chosen = [(f, "train") for f in picks] + [
        (test["frames"][i], "test") for i in _pick(len(test["frames"]), n_test, 1 / 6)
    ]
    tiles = []
    for frame, split in chosen:
        image = Image.open(dataset / f"{frame['file_path']}.png").convert("RGB").resize((tile, tile))
        tiles.append((image, _caption(frame, split)))
    return train, tiles


def make_contact_sheet(
    datasets: list[Path], out_path: Path, n_train: int = 3, n_test: int = 3, tile: int = 128
) -> Path:
    """Write the sheet PNG: per dataset, ``n_train`` training views (across settings) and ``n_test``
    views from the test path, each captioned with its parameter values."""
    font = ImageFont.load_default()
    label_width, caption, gap = 170, 14, 4
    columns = n_train + n_test
    width = label_width + columns * (tile + gap)
    row_height = tile + caption + gap
    sheet = Image.new("RGB", (width, 20 + row_height * len(datasets)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c in range(columns):
        draw.text(
            (label_width + c * (tile + gap) + 4, 4),
            "train" if c < n_train else "test path",
            fill=(0, 0, 0),
            font=font,
        )
    for r, dataset in enumerate(datasets):
        document, tiles = _dataset_tiles(dataset, n_train, n_test, tile)
        top = 20 + r * row_height
        scene = document.get("scene", {})
        names = document.get("param_names", [])
        lines = [scene.get("name", dataset.name), f"{scene.get('kind', '?')}, K={len(names)}", *names]
        for i, line in enumerate(lines):
            draw.text((4, top + 4 + 12 * i), line, fill=(0, 0, 0), font=font)
        for c, (image, text) in enumerate(tiles):
            left = label_width + c * (tile + gap)
            sheet.paste(image, (left, top))
            draw.rectangle((left, top, left + tile - 1, top + tile - 1), outline=(200, 200, 200))
            draw.text((left + 2, top + tile + 1), text, fill=(60, 60, 60), font=font)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_path)
    return out_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+", type=Path, help="dataset folders written by make-scene")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--tile", type=int, default=128, help="tile size in pixels")
    args = parser.parse_args(argv)
    make_contact_sheet(args.datasets, args.out, tile=args.tile)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
