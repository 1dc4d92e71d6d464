"""Image quality metrics. Images are float arrays in [0, 1], shape [h, w, 3]."""

import math

import numpy as np


def mse_to_psnr(mse: float, data_range: float = 1.0) -> float:
    """PSNR in dB of a mean squared error; ``inf`` for a perfect match."""
    if mse < 0 or not math.isfinite(mse):
        raise ValueError(f"mse must be finite and non-negative, got {mse}")
    if mse == 0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / mse)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two images in [0, 1]."""
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    return mse_to_psnr(float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM (scikit-image, Gaussian weights as in the NeRF literature, data range 1, colour)."""
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    # Imported here: scikit-image is in the `train` extra, and the server (which imports this module
    # through the command line) must start without it.
    from skimage.metrics import structural_similarity

    return float(
        structural_similarity(
            a.astype(np.float64), b.astype(np.float64), data_range=1.0, channel_axis=-1,
            gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        )
    )
