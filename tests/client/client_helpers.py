"""Helpers shared by the browser tests (a uniquely named module, imported by the tests)."""

import base64
import io
import json
import urllib.request
from pathlib import Path

import numpy as np
from PIL import Image

ARTIFACTS = Path(__file__).resolve().parents[1] / "_artifacts"


def wait_for_full_frame(page, after_seq: int = 0, selector: str = "#canvas-a") -> int:
    """Wait until the view has settled: every active canvas shows the full-quality frame of its
    newest request, and ``selector``'s frame is newer than ``after_seq``. Returns that seq."""
    page.wait_for_function(
        """([sel, after]) => {
            const c = document.querySelector(sel);
            return window.__visnerfSettled && window.__visnerfSettled()
                && c && c.dataset.quality === "full" && Number(c.dataset.seq) > after;
        }""",
        arg=[selector, after_seq],
    )
    return int(page.locator(selector).get_attribute("data-seq"))


def canvas_pixels(page, selector: str = "#canvas-a") -> np.ndarray:
    """The canvas content as an (h, w, 3) uint8 array (read back through a PNG data URL)."""
    data_url = page.eval_on_selector(selector, "c => c.toDataURL('image/png')")
    png = base64.b64decode(data_url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def decode_png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def camera_readout(page) -> tuple[float, float, float]:
    return (
        float(page.inner_text("#az-value")),
        float(page.inner_text("#el-value")),
        float(page.inner_text("#dist-value")),
    )


def get_json(url: str) -> object:
    with urllib.request.urlopen(url, timeout=10) as response:
        return json.loads(response.read())


def get_bytes(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=30) as response:
        return response.read()


def assert_changed(before: np.ndarray, after: np.ndarray) -> None:
    """The picture changed: same size, and over 5% of the pixels moved by more than 2 levels.

    Both are lossless full-quality frames of a deterministic renderer, so any change is real.
    """
    assert before.shape == after.shape
    delta = np.abs(before.astype(int) - after.astype(int)).max(axis=-1)
    changed = (delta > 2).mean()
    assert changed > 0.05, f"the picture did not change ({100 * changed:.2f}% of pixels moved by more than 2)"
