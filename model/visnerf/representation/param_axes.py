"""CP factorisation over the parameter axes: one learnable vector per axis.

Each axis ``k`` holds a table ``[n_values_k, n_components]`` whose rows sit at the axis's training
values (normalised to [-1, 1]). ``sample(params)`` interpolates each table at the normalised
parameter value, a monotone cubic through the rows (``interpolate_knots``), and multiplies the axes
together: ``[n, n_components]``. Tables start at one, so a fresh field ignores its parameters; with
K = 0 the features are ones. Differentiable in the tables.

Training sees the tables only at their knots, where every interpolant gives the row itself, so the
interpolant decides nothing but the frames between training values. A feature that a parameter
moves along a curve is followed along the curve instead of its chords: the monotone cubic beats
the paper's piecewise-linear interpolant between training values (docs/decisions.md#param.interpolant).
"""

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn


def distinct_rows(params: Float[Tensor, "n k"]) -> tuple[Float[Tensor, "s k"], Int[Tensor, " n"]]:
    """``torch.unique(params, dim=0, return_inverse=True)`` (rows sorted, k >= 1) by one sort per
    column and one of a whole-number key: unique over rows sorts whole rows, a measurable part of
    a training step (docs/decisions.md#param.distinct_rows)."""
    n = params.shape[0]
    key = torch.zeros(n, dtype=torch.long, device=params.device)
    for k in range(params.shape[1]):
        values, rank = torch.unique(params[:, k], return_inverse=True)
        key = key * values.numel() + rank
    keys, which = torch.unique(key, return_inverse=True)
    first = torch.empty(keys.numel(), dtype=torch.long, device=params.device)
    first.scatter_(0, which, torch.arange(n, device=params.device))  # any row of a group: they are equal
    return params.index_select(0, first), which


def pchip_slopes(table: Float[Tensor, "m c"], knots: Float[Tensor, " m"]) -> Float[Tensor, "m c"]:
    """Derivatives at the knots of the monotone piecewise cubic Hermite interpolant of each column
    (Fritsch and Butland's weighted harmonic mean of the neighbouring secants, with the three-point
    shape-preserving ends: the scheme of ``scipy.interpolate.PchipInterpolator``). A knot where a
    column turns, or next to a flat secant, gets slope 0, so each piece stays between its two knot
    values: no overshoot. Two knots: the secant at both (the interpolant is then linear).
    Differentiable in ``table``; every division is by a nonzero value."""
    h = (knots[1:] - knots[:-1])[:, None]  # [m-1, 1], positive (strictly increasing knots)
    secant = (table[1:] - table[:-1]) / h  # [m-1, c]
    if table.shape[0] == 2:
        return torch.cat([secant, secant], dim=0)
    w1, w2 = 2.0 * h[1:] + h[:-1], h[1:] + 2.0 * h[:-1]  # [m-2, 1]
    turn = secant[1:] * secant[:-1] <= 0.0  # [m-2, c]: a sign change or a flat secant
    left, right = torch.where(turn, 1.0, secant[:-1]), torch.where(turn, 1.0, secant[1:])
    inner = torch.where(turn, 0.0, (w1 + w2) / (w1 / left + w2 / right))
    first = _end_slope(h[0], h[1], secant[0], secant[1])
    last = _end_slope(h[-1], h[-2], secant[-1], secant[-2])
    return torch.cat([first[None], inner, last[None]], dim=0)


def _end_slope(h0: Tensor, h1: Tensor, s0: Float[Tensor, " c"], s1: Float[Tensor, " c"]) -> Float[Tensor, " c"]:
    """Slope at an end knot from its secant ``s0`` and the next one ``s1`` (interval widths h0, h1):
    the three-point estimate, set to 0 where its sign differs from ``s0``'s and limited to ``3 s0``
    where the data turn at the next knot."""
    d = ((2.0 * h0 + h1) * s0 - h0 * s1) / (h0 + h1)
    d = torch.where(torch.sign(d) != torch.sign(s0), 0.0, d)
    limit = (torch.sign(s0) != torch.sign(s1)) & (d.abs() > 3.0 * s0.abs())
    return torch.where(limit, 3.0 * s0, d)


def _pieces(knots: Float[Tensor, " m"], x: Float[Tensor, " n"]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The piece of at least two strictly increasing ``knots`` that holds each ``x`` (clamped to
    the knots): its lower and upper knot indices, its width and ``x``'s place in it, in [0, 1]."""
    x = x.clamp(float(knots[0]), float(knots[-1]))
    hi = torch.searchsorted(knots, x.contiguous()).clamp(1, knots.shape[0] - 1)  # [n]
    lo = hi - 1
    span = (knots[hi] - knots[lo]).clamp_min(torch.finfo(knots.dtype).eps)  # [n]
    return lo, hi, span, ((x - knots[lo]) / span).clamp(0.0, 1.0)


def knot_rows(knots: Float[Tensor, " m"], x: Float[Tensor, " n"]) -> Int[Tensor, " n"] | None:
    """The index of each ``x`` among strictly increasing ``knots`` where every ``x`` is exactly a
    knot, else None. Every interpolant here gives a knot's own row there, in value and gradient
    (its other terms are multiplied by an exact 0), and training reads the tables only at their
    knots: their rows are then gathered, not interpolated (a late Nyx step's parameter features
    were some 700 of its 2,600 torch operations)."""
    index = torch.searchsorted(knots, x.contiguous()).clamp_max(knots.shape[0] - 1)
    return index if bool((knots.index_select(0, index) == x).all()) else None


def interpolate_knots(
    table: Float[Tensor, "m c"], knots: Float[Tensor, " m"], x: Float[Tensor, " n"]
) -> Float[Tensor, "n c"]:
    """Table rows placed at strictly increasing ``knots``, interpolated at ``x`` by the monotone
    cubic through them (``pchip_slopes``); held at the end rows outside the knots."""
    if knots.shape[0] == 1:
        return table.expand(x.shape[0], -1)
    at_knots = knot_rows(knots, x)
    if at_knots is not None:
        return table.index_select(0, at_knots)
    lo, hi, span, s = _pieces(knots, x)
    s = s.unsqueeze(-1)  # [n, 1]
    slopes = pchip_slopes(table, knots)  # [m, c]
    s2, s3 = s * s, s * s * s
    h00, h10 = 2.0 * s3 - 3.0 * s2 + 1.0, s3 - 2.0 * s2 + s  # cubic Hermite basis
    h01, h11 = 3.0 * s2 - 2.0 * s3, s3 - s2
    width = span.unsqueeze(-1)  # [n, 1]
    return (h00 * table.index_select(0, lo) + h01 * table.index_select(0, hi)
            + width * (h10 * slopes.index_select(0, lo) + h11 * slopes.index_select(0, hi)))


def natural_spline_curvatures(table: Float[Tensor, " m"], knots: Float[Tensor, " m"]) -> Float[Tensor, " m"]:
    """Second derivatives at the knots of the natural cubic spline through ``(knots, table)``: zero
    at both ends, and at the inner knots the solution of the spline's continuity equations
    ``h_{i-1} M_{i-1} + 2 (h_{i-1} + h_i) M_i + h_i M_{i+1} = 6 (secant_i - secant_{i-1})``
    (a small dense solve: an axis has at most a few dozen values). Differentiable in ``table``."""
    m = table.shape[0]
    if m < 3:
        return torch.zeros_like(table)
    h = knots[1:] - knots[:-1]  # [m-1], positive
    secant = (table[1:] - table[:-1]) / h  # [m-1]
    system = torch.diag(2.0 * (h[:-1] + h[1:]))  # [m-2, m-2]
    if m > 3:
        system = system + torch.diag(h[1:-1], 1) + torch.diag(h[1:-1], -1)
    inner = torch.linalg.solve(system, 6.0 * (secant[1:] - secant[:-1]))  # [m-2]
    zero = table.new_zeros(1)
    return torch.cat([zero, inner, zero])


def interpolate_natural_spline(
    table: Float[Tensor, " m"], knots: Float[Tensor, " m"], x: Float[Tensor, " n"]
) -> Float[Tensor, " n"]:
    """The natural cubic spline through the values ``table`` at strictly increasing ``knots``,
    at ``x``; held at the end values outside the knots, and each piece kept between its two knot
    values (a spline through steep data may overshoot between them; these values may not)."""
    if knots.shape[0] == 1:
        return table.expand(x.shape[0])
    at_knots = knot_rows(knots, x)
    if at_knots is not None:
        return table.index_select(0, at_knots)
    lo, hi, span, b = _pieces(knots, x)
    a = 1.0 - b
    curv = natural_spline_curvatures(table, knots)  # [m]
    y_lo, y_hi = table[lo], table[hi]
    y = a * y_lo + b * y_hi + ((a**3 - a) * curv[lo] + (b**3 - b) * curv[hi]) * span * span / 6.0
    return torch.minimum(torch.maximum(y, torch.minimum(y_lo, y_hi)), torch.maximum(y_lo, y_hi))


class ParamAxes(nn.Module):
    """The CP parameter vectors of one branch (density or appearance)."""

    def __init__(self, param_lengths: tuple[int, ...], n_components: int) -> None:
        super().__init__()
        self.n_components = n_components
        self.tables = nn.ParameterList([nn.Parameter(torch.ones(n, n_components)) for n in param_lengths])
        for k, n in enumerate(param_lengths):
            # Default: evenly spaced knots; set_knots() places them at the real training values.
            self.register_buffer(f"knots_{k}", torch.linspace(-1.0, 1.0, n) if n > 1 else torch.zeros(1))

    @property
    def n_params(self) -> int:
        return len(self.tables)

    def knots(self, k: int) -> Tensor:
        return getattr(self, f"knots_{k}")

    @torch.no_grad()
    def set_knots(self, k: int, knots: Float[Tensor, " m"]) -> None:
        """Place axis ``k``'s rows at these normalised training values (strictly increasing)."""
        if knots.shape != self.knots(k).shape:
            raise ValueError(f"axis {k} has {self.knots(k).shape[0]} values, got {knots.shape[0]} knots")
        if knots.numel() > 1 and not bool((knots[1:] > knots[:-1]).all()):
            raise ValueError(f"knots of axis {k} must be strictly increasing")
        self.knots(k).copy_(knots)

    def sample(self, params: Float[Tensor, "n k"]) -> Float[Tensor, "n c"]:
        """Product over axes of the interpolated vectors at normalised ``params``."""
        out = torch.ones(params.shape[0], self.n_components, device=params.device, dtype=params.dtype)
        for k, table in enumerate(self.tables):
            out = out * interpolate_knots(table, self.knots(k), params[:, k])
        return out

    def l1_to_one(self) -> Tensor:
        """Mean |1 - w| over all tables (0 for K = 0)."""
        if not self.tables:
            return torch.zeros(())
        return sum((1.0 - t).abs().mean() for t in self.tables) / len(self.tables)

    def total_variation(self) -> Tensor:
        """Mean squared difference of neighbouring rows (0 for K = 0 and single-value axes)."""
        terms = [(t[1:] - t[:-1]).pow(2).mean() for t in self.tables if t.shape[0] > 1]
        if not terms:
            return torch.zeros(())
        return sum(terms) / len(terms)


class LevelAxis(nn.Module):
    """The level of an isovalue axis: one learnt scalar per training value, interpolated by the
    natural cubic spline (``interpolate_natural_spline``).

    An isosurface at isovalue ``v`` is the level set ``{f = v}`` of one scalar field ``f``, and the
    surfaces of a sweep are nested. The field models that directly: its density branch computes
    ``g(x)`` without this axis's factors and subtracts ``level(v)`` before the softplus, so every
    isovalue's surface is a level set of the same ``g`` and a value between two training values
    gives the level set between theirs. Any increasing or decreasing reparameterisation of the
    isovalue is absorbed by ``g``, so a scalar per training value is general. The levels start at
    zero (every isovalue the same surface) and are pulled apart by the images.

    Training sees the levels only at their knots; the interpolant places every surface between
    them. The levels of a trained sweep are a smooth function of the isovalue, which the natural
    spline (twice continuously differentiable) follows more closely than the monotone cubic of
    the parameter tables, whose slopes are held back at each knot (docs/decisions.md#param.interpolant).
    Each piece is kept between its two knot values.

    ``sharpness`` multiplies ``g(x) - level(v)``. A surface is opaque where that difference has
    risen by some ten units, so with a fixed scale the field must rise steeply at the training
    surfaces and stay flat between them, and a value between the training values then finds a flat
    ``g``: a half-transparent surface. The sharpness is learnt in log space (Adam moves it by about
    the learning rate a step whatever its gradient's size), so it can grow by orders of magnitude,
    and ``g`` stays a smooth field whose every level set is sharp."""

    def __init__(self, n_values: int) -> None:
        super().__init__()
        self.table = nn.Parameter(torch.zeros(n_values, 1))
        self.log_sharpness = nn.Parameter(torch.zeros(()))
        self.register_buffer("knots", torch.linspace(-1.0, 1.0, n_values) if n_values > 1 else torch.zeros(1))

    @torch.no_grad()
    def set_knots(self, knots: Float[Tensor, " m"]) -> None:
        """Place the levels at these normalised training values (strictly increasing)."""
        if knots.shape != self.knots.shape:
            raise ValueError(f"the level axis has {self.knots.shape[0]} values, got {knots.shape[0]} knots")
        if knots.numel() > 1 and not bool((knots[1:] > knots[:-1]).all()):
            raise ValueError("knots of the level axis must be strictly increasing")
        self.knots.copy_(knots)

    def sharpness(self) -> Tensor:
        """The factor on ``g(x) - level(v)`` (0-d)."""
        return self.log_sharpness.exp()

    def sample(self, values: Float[Tensor, " n"]) -> Float[Tensor, " n"]:
        """The level at normalised values; held at the end levels outside the knots."""
        return interpolate_natural_spline(self.table[:, 0], self.knots, values)
