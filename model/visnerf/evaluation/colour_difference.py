"""Colour difference in CIELUV, as the paper shows its difference images, and a fixed colour legend.

Conversion: sRGB (IEC 61966-2-1 transfer curve) -> linear RGB -> CIE XYZ (D65, 2 degree observer)
-> CIE L*u*v*. The difference of two images is the Euclidean distance of their L*u*v* values per
pixel (Delta E*uv; L* runs 0..100, so black to white is 100). Difference images map that distance
through one fixed legend, ``0 .. DIFFERENCE_SCALE_MAX``, so images of different frames, scenes and
models can be compared by eye; larger values take the top colour.
"""

import numpy as np
from jaxtyping import Float, UInt8

# sRGB primaries to XYZ, D65 white (IEC 61966-2-1).
_SRGB_TO_XYZ = np.array(
    [
        [0.4124564, 0.3575761, 0.1804375],
        [0.2126729, 0.7151522, 0.0721750],
        [0.0193339, 0.1191920, 0.9503041],
    ]
)
D65_WHITE = (0.95047, 1.0, 1.08883)
"""XYZ of the D65 reference white (Y = 1)."""
_EPSILON = (6.0 / 29.0) ** 3  # CIE: below this Y/Yn, L* is linear in Y
_KAPPA = (29.0 / 3.0) ** 3

DIFFERENCE_SCALE_MAX = 30.0
"""Delta E*uv at the top of the legend (values above it take the top colour)."""
LEGEND_STOPS: tuple[tuple[float, tuple[float, float, float]], ...] = (
    (0.0, (1.0, 1.0, 1.0)),  # no difference: white, like the background
    (0.1, (1.0, 0.93, 0.55)),
    (0.3, (0.99, 0.66, 0.20)),
    (0.55, (0.89, 0.26, 0.10)),
    (0.8, (0.60, 0.05, 0.22)),
    (1.0, (0.22, 0.0, 0.28)),
)
"""The fixed legend: (fraction of the scale, sRGB colour), linearly interpolated in between."""


def srgb_to_linear(rgb: Float[np.ndarray, "*batch 3"]) -> Float[np.ndarray, "*batch 3"]:
    """Undo the sRGB transfer curve; input in [0, 1]."""
    c = np.clip(rgb.astype(np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def srgb_to_xyz(rgb: Float[np.ndarray, "*batch 3"]) -> Float[np.ndarray, "*batch 3"]:
    """CIE XYZ (D65, white Y = 1) of sRGB colours in [0, 1]."""
    return srgb_to_linear(rgb) @ _SRGB_TO_XYZ.T


def xyz_to_luv(
    xyz: Float[np.ndarray, "*batch 3"], white: tuple[float, float, float] = D65_WHITE
) -> Float[np.ndarray, "*batch 3"]:
    """CIE L*u*v* of XYZ colours relative to ``white``. Black (X + 15Y + 3Z = 0) maps to (0, 0, 0)."""
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    xn, yn, zn = white
    yr = y / yn
    lightness = np.where(yr > _EPSILON, 116.0 * np.cbrt(yr) - 16.0, _KAPPA * yr)
    denom = x + 15.0 * y + 3.0 * z
    safe = np.where(denom > 0, denom, 1.0)
    u_prime = np.where(denom > 0, 4.0 * x / safe, 0.0)
    v_prime = np.where(denom > 0, 9.0 * y / safe, 0.0)
    denom_n = xn + 15.0 * yn + 3.0 * zn
    u = 13.0 * lightness * (u_prime - 4.0 * xn / denom_n)
    v = 13.0 * lightness * (v_prime - 9.0 * yn / denom_n)
    return np.stack([lightness, u, v], axis=-1)


def srgb_to_luv(rgb: Float[np.ndarray, "*batch 3"]) -> Float[np.ndarray, "*batch 3"]:
    """CIE L*u*v* (D65) of sRGB colours in [0, 1]."""
    return xyz_to_luv(srgb_to_xyz(rgb))


def luv_difference(a: Float[np.ndarray, "h w 3"], b: Float[np.ndarray, "h w 3"]) -> Float[np.ndarray, "h w"]:
    """Delta E*uv per pixel of two sRGB images in [0, 1]: zero for identical images, symmetric."""
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    return np.linalg.norm(srgb_to_luv(a) - srgb_to_luv(b), axis=-1)


def legend_colours(
    fraction: Float[np.ndarray, "*batch"],
) -> Float[np.ndarray, "*batch 3"]:
    """Legend colour (sRGB in [0, 1]) at ``fraction`` of the scale; clipped to [0, 1]."""
    f = np.clip(np.asarray(fraction, dtype=np.float64), 0.0, 1.0)
    stops = np.array([s for s, _ in LEGEND_STOPS])
    colours = np.array([c for _, c in LEGEND_STOPS])
    return np.stack([np.interp(f, stops, colours[:, ch]) for ch in range(3)], axis=-1)


def colourize_difference(
    delta: Float[np.ndarray, "h w"], scale_max: int | float = DIFFERENCE_SCALE_MAX
) -> UInt8[np.ndarray, "h w 3"]:
    """The difference image: Delta E*uv mapped through the fixed legend ``0 .. scale_max``."""
    if not scale_max > 0:
        raise ValueError(f"the legend's top value must be positive, got {scale_max}")
    rgb = legend_colours(delta / float(scale_max))  # [h, w, 3]
    return (rgb * 255.0 + 0.5).astype(np.uint8)
