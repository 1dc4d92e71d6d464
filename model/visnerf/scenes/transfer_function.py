"""Piecewise-linear transfer functions (colour and opacity over the field value) and the TF schemes.

Opacity convention: a TF opacity ``a`` is the opacity of a slab ``reference_step`` thick (world
units), as in classical volume renderers. A renderer that marches with step ``dt`` uses the
corrected opacity ``1 - (1 - a) ** (dt / reference_step)``, i.e. the extinction coefficient
``sigma = -log(1 - a) / reference_step``, so the image does not depend on the step. Colours are
display RGB in [0, 1], not premultiplied.
"""

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class TransferFunction:
    """Colour and opacity as piecewise-linear functions of the value, constant beyond the ends."""

    knots: tuple[float, ...]
    """Strictly increasing control values (at least two)."""
    colours: tuple[RGB, ...]
    """RGB in [0, 1] at each knot."""
    opacities: tuple[float, ...]
    """Opacity in [0, 1] at each knot, for a slab ``reference_step`` thick."""
    reference_step: float = 0.01
    """Thickness (world units) the opacities refer to."""
    max_opacity: float = 1.0 - 1e-6
    """Opacities are clamped to this before the extinction is taken, so ``a = 1`` stays finite."""

    def __post_init__(self) -> None:
        n = len(self.knots)
        if n < 2 or len(self.colours) != n or len(self.opacities) != n:
            raise ValueError("a transfer function needs >= 2 knots and one colour and opacity per knot")
        if any(b <= a for a, b in zip(self.knots, self.knots[1:], strict=False)):
            raise ValueError(f"knots must be strictly increasing, got {self.knots}")
        if any(not 0.0 <= o <= 1.0 for o in self.opacities):
            raise ValueError(f"opacities must lie in [0, 1], got {self.opacities}")
        if any(not 0.0 <= c <= 1.0 for rgb in self.colours for c in rgb):
            raise ValueError("colours must lie in [0, 1]")
        if not self.reference_step > 0.0:
            raise ValueError(f"reference_step must be positive, got {self.reference_step}")

    def _interpolate(self, values: Tensor, table: Tensor) -> Tensor:
        # Exact piecewise-linear interpolation as a sum of clamped ramps, one per interval:
        # f(v) = f_0 + sum_i clamp(v - k_i, 0, k_{i+1} - k_i) * slope_i (constant beyond the ends).
        knots = torch.tensor(self.knots, dtype=values.dtype, device=values.device)  # [m]
        widths = knots[1:] - knots[:-1]  # [m - 1]
        slopes = (table[1:] - table[:-1]) / widths[:, None]  # [m - 1, c]
        ramps = torch.minimum((values[:, None] - knots[:-1]).clamp_min(0.0), widths)  # [n, m - 1]
        return table[0] + ramps @ slopes  # [n, c]

    def colour(self, values: Float[Tensor, " n"]) -> Float[Tensor, "n 3"]:
        """RGB at each value (linear interpolation between knots)."""
        table = torch.tensor(self.colours, dtype=values.dtype, device=values.device)  # [m, 3]
        return self._interpolate(values, table)

    def opacity(self, values: Float[Tensor, " n"]) -> Float[Tensor, " n"]:
        """TF opacity (for ``reference_step``) at each value."""
        table = torch.tensor(self.opacities, dtype=values.dtype, device=values.device)[:, None]  # [m, 1]
        return self._interpolate(values, table)[:, 0]

    def extinction(self, values: Float[Tensor, " n"]) -> Float[Tensor, " n"]:
        """Extinction coefficient sigma = -log(1 - a) / reference_step (per world unit)."""
        return self._opacity_to_extinction(self.opacity(values))

    def colour_and_extinction(
        self, values: Float[Tensor, " n"]
    ) -> tuple[Float[Tensor, "n 3"], Float[Tensor, " n"]]:
        """RGB and extinction at each value with a single knot search."""
        table = torch.tensor(
            [(*rgb, a) for rgb, a in zip(self.colours, self.opacities, strict=True)],
            dtype=values.dtype,
            device=values.device,
        )  # [m, 4]
        rgba = self._interpolate(values, table)  # [n, 4]
        return rgba[:, :3], self._opacity_to_extinction(rgba[:, 3])

    def _opacity_to_extinction(self, alpha: Tensor) -> Tensor:
        return -torch.log1p(-alpha.clamp(max=self.max_opacity)) / self.reference_step


def corrected_opacity(
    opacity: Float[Tensor, "*shape"], step: float, reference_step: float
) -> Float[Tensor, "*shape"]:
    """Opacity of a slab ``step`` thick given the opacity ``opacity`` of one ``reference_step`` thick."""
    return -torch.expm1(torch.log1p(-opacity) * (step / reference_step))


def constant_extinction_tf(
    sigma: float, colour: RGB = (0.0, 0.0, 0.0), reference_step: float = 0.01
) -> TransferFunction:
    """A TF with extinction ``sigma`` (per world unit) and one colour for every value."""
    alpha = -math.expm1(-sigma * reference_step)
    return TransferFunction((-1e9, 1e9), (colour, colour), (alpha, alpha), reference_step)


def _plasma(t: float) -> RGB:
    """A plasma-like colour map (dark blue-violet, magenta, orange, yellow) at t in [0, 1]."""
    stops = (
        (0.05, 0.03, 0.53),
        (0.42, 0.00, 0.66),
        (0.69, 0.17, 0.56),
        (0.88, 0.39, 0.34),
        (0.99, 0.65, 0.15),
        (0.94, 0.98, 0.13),
    )
    x = min(max(t, 0.0), 1.0) * (len(stops) - 1)
    i = min(int(x), len(stops) - 2)
    f = x - i
    a, b = stops[i], stops[i + 1]
    return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))


def _lerp_rgb(a: RGB, b: RGB, t: float) -> RGB:
    return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))


def plume_tf() -> TransferFunction:
    """Plume density: transparent below 0.05, then plasma colours (violet to yellow), rising opacity."""
    knots = (0.05, 0.25, 0.5, 0.75, 0.95)
    opacities = (0.0, 0.03, 0.1, 0.3, 0.6)
    return TransferFunction(knots, tuple(_plasma(t) for t in (0.0, 0.25, 0.5, 0.75, 1.0)), opacities)


def two_range_tf(opacity_low: float, opacity_high: float) -> TransferFunction:
    """TF-1: a blue-cyan sheath range [0.15, 0.45] and an orange-red core range [0.6, 1.0].

    The two parameters are the opacities of the two ranges (the paper's TF-1 scheme).
    """
    blue, cyan = (0.12, 0.35, 0.85), (0.2, 0.8, 0.9)
    orange, red = (1.0, 0.6, 0.1), (0.8, 0.05, 0.05)
    knots = (0.1, 0.15, 0.45, 0.5, 0.55, 0.6, 1.0)
    colours = (blue, blue, cyan, cyan, orange, orange, red)
    opacities = (0.0, opacity_low, opacity_low, 0.0, 0.0, opacity_high, opacity_high)
    return TransferFunction(knots, colours, opacities)


def translated_range_tf(shift: float) -> TransferFunction:
    """TF-2: one visible range moved from the sheath (0.3, blue) onto the core (0.8, red).

    ``shift`` in [0, 1] translates the range's centre linearly and interpolates its colour and
    opacity between the two ends (the paper's TF-2 scheme).
    """
    centre = 0.3 + 0.5 * shift
    colour = _lerp_rgb((0.1, 0.3, 0.9), (0.85, 0.1, 0.05), shift)
    alpha = 0.12 + (0.6 - 0.12) * shift
    knots = (centre - 0.12, centre - 0.05, centre + 0.05, centre + 0.12)
    return TransferFunction(knots, (colour,) * 4, (0.0, alpha, alpha, 0.0))


def cosmic_tf() -> TransferFunction:
    """Cosmic web: voids transparent, filaments violet, knots orange to yellow."""
    knots = (0.15, 0.35, 0.55, 0.8, 1.0)
    opacities = (0.0, 0.01, 0.06, 0.3, 0.6)
    return TransferFunction(knots, tuple(_plasma(t) for t in (0.0, 0.25, 0.5, 0.8, 1.0)), opacities)


def peaks_tf(peaks: tuple[tuple[float, RGB, float], ...], half_width: float, ends: tuple[RGB, RGB]) -> TransferFunction:
    """Narrow triangular opacity peaks (centre, colour, opacity), ``half_width`` either side, each
    in its colour, transparent between them and beyond; ``ends`` colour values 0 and 1."""
    knots, colours, opacities = [0.0], [ends[0]], [0.0]
    for centre, colour, alpha in peaks:
        knots += [centre - half_width, centre, centre + half_width]
        colours += [colour] * 3
        opacities += [0.0, alpha, 0.0]
    knots.append(1.0)
    colours.append(ends[1])
    opacities.append(0.0)
    return TransferFunction(tuple(knots), tuple(colours), tuple(opacities))


def shells_tf() -> TransferFunction:
    """Three translucent shells: narrow opacity peaks at values 0.25 (blue), 0.5 (green) and 0.75
    (orange), transparent between them, as a contour-style transfer function draws surfaces."""
    peaks = ((0.25, (0.15, 0.4, 0.95), 0.35), (0.5, (0.2, 0.8, 0.35), 0.5), (0.75, (1.0, 0.55, 0.1), 0.8))
    return peaks_tf(peaks, 0.04, ((0.1, 0.3, 0.9), (1.0, 0.55, 0.1)))


def nested_shells_tf() -> TransferFunction:
    """Nested shells around every blob: narrow opacity peaks at 0.3 (a faint blue outer shell),
    0.55 (a green middle one) and 0.8 (a nearly opaque orange core), transparent between them, as a
    scientist's contour-style transfer function picks a few values of a turbulent field."""
    peaks = ((0.3, (0.2, 0.45, 1.0), 0.22), (0.55, (0.35, 0.85, 0.3), 0.45), (0.8, (1.0, 0.45, 0.1), 0.9))
    return peaks_tf(peaks, 0.03, ((0.2, 0.45, 1.0), (1.0, 0.45, 0.1)))
