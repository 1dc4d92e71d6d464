"""Decoding a dataset's images: uint8 RGB, RGBA composited on the background with its alpha kept,
one size for all."""

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import UInt8
from PIL import Image
from torch import Tensor

from visnerf.data.errors import DatasetError

DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError)
"""What Pillow raises for a file that is not an image, is truncated or is corrupted."""


def composite(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """uint8 RGB of a uint8 RGBA image [h, w, 4] over ``background`` (3 floats in [0, 1])."""
    f = rgba.astype(np.float32) / 255.0
    rgb = f[..., :3] * f[..., 3:] + background * (1.0 - f[..., 3:])
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


def composite_keeping_alpha(rgba: np.ndarray, background: np.ndarray) -> np.ndarray:
    """uint8 [h, w, 4]: ``composite``'s RGB and the image's own alpha as the fourth channel."""
    return np.concatenate([composite(rgba, background), rgba[..., 3:]], axis=-1)


def load_rgb(path: Path, background: np.ndarray, label: str) -> np.ndarray:
    """The image as uint8 RGB [h, w, 3], or for an image with transparency RGB composited on
    ``background`` and its alpha [h, w, 4]; refused when it cannot be decoded."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
                return composite_keeping_alpha(np.asarray(im.convert("RGBA")), background)
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except DECODE_ERRORS as exc:
        raise DatasetError(f"{label}: cannot decode image {path}: {exc}") from None


@dataclass(frozen=True)
class DecodedImages:
    """A split's pixels: colours composited on the background, and the opacities where any image
    has some pixel that is not opaque (frames without transparency: 255)."""

    rgb: UInt8[Tensor, "n h w 3"]
    alpha: UInt8[Tensor, "n h w"] | None


def _size_error(labels: Sequence[str], i: int, shape: tuple[int, ...], first: tuple[int, ...], differ: int) -> DatasetError:
    return DatasetError(f"images differ in size: {labels[i]} is {shape[1]}x{shape[0]}, {labels[0]} is "
                        f"{first[1]}x{first[0]} ({differ} frame(s) differ from the first)")


def load_images(
    paths: Sequence[Path],
    labels: Sequence[str],
    background: np.ndarray,
    max_workers: int,
    decode: Callable[[Path, np.ndarray, str], np.ndarray] = load_rgb,
) -> DecodedImages:
    """The images, checked decodable (by ``decode``: [h, w, 3] RGB or [h, w, 4] RGB and alpha)
    and of one size, each copied into the split's arrays as it is decoded (one image's copy at a
    time, not the split's)."""
    rgb: Tensor | None = None
    alpha: Tensor | None = None
    first: tuple[int, ...] = ()
    bad: list[tuple[int, tuple[int, ...]]] = []
    with ThreadPoolExecutor(max_workers=max_workers) as pool:
        for i, image in enumerate(pool.map(lambda p, label: decode(p, background, label), paths, labels)):
            if rgb is None:
                first = image.shape[:2]
                rgb = torch.empty((len(paths), *first, 3), dtype=torch.uint8)
            if image.shape[:2] != first:
                bad.append((i, image.shape[:2]))
                continue
            rgb[i].numpy()[...] = image[..., :3]
            if image.shape[2] == 4 and (alpha is not None or bool((image[..., 3] < 255).any())):
                if alpha is None:
                    alpha = torch.full((len(paths), *first), 255, dtype=torch.uint8)
                alpha[i].numpy()[...] = image[..., 3]
    if bad:
        raise _size_error(labels, bad[0][0], bad[0][1], first, len(bad))
    if rgb is None:
        raise DatasetError("no images to decode")
    return DecodedImages(rgb, alpha)
