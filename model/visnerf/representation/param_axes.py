"""CP factorisation over the parameter axes: one learnable vector per axis.

Each axis ``k`` holds a table ``[n_values_k, n_components]`` whose rows sit at the axis's training
values (normalised to [-1, 1]). ``sample(params)`` interpolates each table piecewise-linearly at the
normalised parameter value and multiplies the axes together: ``[n, n_components]``. Tables start at
one, so a fresh field ignores its parameters; with K = 0 the features are ones. Differentiable in
the tables.
"""

import torch
from jaxtyping import Float
from torch import Tensor, nn


def interpolate_knots(
    table: Float[Tensor, "m c"], knots: Float[Tensor, " m"], x: Float[Tensor, " n"]
) -> Float[Tensor, "n c"]:
    """Piecewise-linear interpolation of table rows placed at sorted ``knots``; clamped outside."""
    m = knots.shape[0]
    if m == 1:
        return table.expand(x.shape[0], -1)
    x = x.clamp(float(knots[0]), float(knots[-1]))
    hi = torch.searchsorted(knots, x.contiguous()).clamp(1, m - 1)  # [n]
    lo = hi - 1
    span = (knots[hi] - knots[lo]).clamp_min(torch.finfo(knots.dtype).eps)
    frac = ((x - knots[lo]) / span).clamp(0.0, 1.0).unsqueeze(-1)  # [n, 1]
    return table[lo] * (1.0 - frac) + table[hi] * frac


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
