"""Decoding a dataset's images: uint8 RGB, RGBA composited on the background, one size for all."""

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from visnerf.data.errors import DatasetError

DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)
"""What Pillow raises for a file that is not an image, is truncated or is corrupted."""


def composite(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """uint8 RGB of a uint8 RGBA image [h, w, 4] over ``background`` (3 floats in [0, 1])."""
    f = rgba.astype(np.float32) / 255.0
    rgb = f[..., :3] * f[..., 3:] + background * (1.0 - f[..., 3:])
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


def load_rgb(path: Path, background: np.ndarray, label: str) -> np.ndarray:
    """The image as uint8 RGB, RGBA composited on ``background``; refused when it cannot be decoded."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                return composite(np.asarray(im.convert("RGBA")), background)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except DECODE_ERRORS as exc:
        raise DatasetError(f"{label}: cannot decode image {path}: {exc}") from None


def check_same_size(images: list[np.ndarray], labels: list[str]) -> None:
    """Every image has the first frame's size; names the first frame that differs and both sizes."""
    height, width = images[0].shape[:2]
    differ = [i for i, im in enumerate(images) if im.shape[:2] != (height, width)]
    if differ:
        i = differ[0]
        h, w = images[i].shape[:2]
        raise DatasetError(
            f"images differ in size: {labels[i]} is {w}x{h}, {labels[0]} is {width}x{height} "
            f"({len(differ)} frame(s) differ from the first)"
        )


def load_images(
    paths: Sequence[Path],
    labels: Sequence[str],
    background: np.ndarray,
    max_workers: int,
    decode: Callable[[Path, np.ndarray, str], np.ndarray] = load_rgb,
) -> torch.Tensor:
    """The images as one uint8 [n, h, w, 3] tensor, checked decodable (by ``decode``) and of one size."""
    with ThreadPoolExecutor(max_workers=max_workers) as pool:
        images = list(pool.map(lambda p, label: decode(p, background, label), paths, labels))
    check_same_size(images, labels)
    return torch.from_numpy(np.stack(images))
