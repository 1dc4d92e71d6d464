"""Vector-matrix (VM) factorisation of a 3-D feature grid (TensoRF).

Three planes (XY, XZ, YZ) times three lines (Z, Y, X). Grid coordinates are in [-1, 1] with
``align_corners=True``: -1 and +1 are the centres of the first and last grid nodes. Features of
the three modes are concatenated: ``[n, 3 * n_components]``.

``VMGrid.sample`` reads the factors as row tables through ``embedding_bag`` (differentiable in the
factors, not the coordinates: samples sit at fixed positions). Its backward is one weighted
scatter of rows per table. ``grid_sample`` and advanced indexing, its slow reference twin
``VMGrid._sample``, back-propagate through ``grid_sampler_2d_backward`` and
``index_put_(accumulate=True)``, which took 46 % of a Nyx training step on the CPU.
"""

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from visnerf.representation.vm_taps import MODES, TapLayout, lookup_modes


def interpolate_lines(
    lines: Float[Tensor, "c r"], coords: Float[Tensor, " n"]
) -> Float[Tensor, "n c"]:
    """Linear interpolation of ``c`` line factors of length ``r`` at coordinates in [-1, 1]."""
    r = lines.shape[1]
    pos = ((coords.clamp(-1.0, 1.0) + 1.0) * 0.5 * (r - 1)).to(lines.dtype)  # [n]
    lo = pos.floor().clamp(0, max(r - 2, 0)).long()  # [n]
    hi = (lo + 1).clamp(max=r - 1)
    frac = (pos - lo.to(pos.dtype)).unsqueeze(-1)  # [n, 1]
    lines_t = lines.t()  # [r, c]
    return lines_t[lo] * (1.0 - frac) + lines_t[hi] * frac


def sample_plane(
    plane: Float[Tensor, "c h w"], coords: Float[Tensor, "n 2"]
) -> Float[Tensor, "n c"]:
    """Bilinear sample of a plane; ``coords[:, 0]`` runs along w, ``coords[:, 1]`` along h."""
    grid = coords.view(1, -1, 1, 2).to(plane.dtype)
    out = F.grid_sample(plane.unsqueeze(0), grid, mode="bilinear", align_corners=True)  # [1, c, n, 1]
    return out[0, :, :, 0].t()


class VMGrid(nn.Module):
    """Planes and lines of one VM grid; ``sample(coords) -> [n, 3 * n_components]``."""

    def __init__(self, n_components: int, resolution: tuple[int, int, int], init_scale: float) -> None:
        super().__init__()
        self.n_components = n_components
        planes, lines = [], []
        for (a, b), c in MODES:
            planes.append(nn.Parameter(init_scale * torch.randn(n_components, resolution[b], resolution[a])))
            lines.append(nn.Parameter(init_scale * torch.randn(n_components, resolution[c])))
        self.planes = nn.ParameterList(planes)
        self.lines = nn.ParameterList(lines)

    @property
    def resolution(self) -> tuple[int, int, int]:
        res = [0, 0, 0]
        for ((a, b), c), plane, line in zip(MODES, self.planes, self.lines, strict=True):
            res[a], res[b], res[c] = plane.shape[2], plane.shape[1], line.shape[1]
        return (res[0], res[1], res[2])

    def row_tables(self) -> tuple[Float[Tensor, "p c"], Float[Tensor, "l c"]]:
        """The three planes stacked as rows ``[sum h * w, c]`` and the three lines as ``[sum r, c]``
        (the layout of ``TapLayout``); differentiable copies of the factors."""
        planes = torch.cat([p.permute(1, 2, 0).reshape(-1, p.shape[0]) for p in self.planes])
        lines = torch.cat([line.t() for line in self.lines])
        return planes, lines

    def tap_layout(self) -> TapLayout:
        """Tap layout of the current resolution (cached; resampling changes it)."""
        layout = getattr(self, "_layout", None)
        device = self.planes[0].device
        if layout is None or layout.resolution != self.resolution or layout.half_span.device != device:
            layout = TapLayout.of(self.resolution, device)
            self._layout = layout
        return layout

    def sample(self, coords: Float[Tensor, "n 3"]) -> Float[Tensor, "n f"]:
        """Features at grid coordinates in [-1, 1]^3 (outside reads the border). Differentiable in
        the factors only."""
        n, c = coords.shape[0], self.n_components
        taps = self.tap_layout().taps(coords.detach(), self.planes[0].dtype)
        pf, lf = lookup_modes(taps, *self.row_tables())  # [3n, c] each
        return (pf * lf).view(n, 3 * c)

    def _sample(self, coords: Float[Tensor, "n 3"]) -> Float[Tensor, "n f"]:
        """Slow reference of ``sample``: ``grid_sample`` on the planes, indexing on the lines
        (zero outside the planes' border); differentiable in the factors and the coordinates."""
        feats = []
        for ((a, b), c), plane, line in zip(MODES, self.planes, self.lines, strict=True):
            plane_feat = sample_plane(plane, coords[:, [a, b]])  # [n, comps]
            line_feat = interpolate_lines(line, coords[:, c])  # [n, comps]
            feats.append(plane_feat * line_feat)
        return torch.cat(feats, dim=-1)

    def l1(self) -> Tensor:
        """Mean absolute value of planes and lines (sparsity prior)."""
        total = sum(p.abs().mean() for p in self.planes) + sum(line.abs().mean() for line in self.lines)
        return total / (2 * len(self.planes))

    def total_variation(self) -> Tensor:
        """Mean squared difference of neighbouring entries of planes and lines."""
        total = torch.zeros((), device=self.planes[0].device)
        for plane, line in zip(self.planes, self.lines, strict=True):
            total = total + (plane[:, 1:, :] - plane[:, :-1, :]).pow(2).mean()
            total = total + (plane[:, :, 1:] - plane[:, :, :-1]).pow(2).mean()
            total = total + (line[:, 1:] - line[:, :-1]).pow(2).mean()
        return total / len(self.planes)

    @torch.no_grad()
    def resample(
        self,
        resolution: tuple[int, int, int],
        lower: Float[Tensor, " 3"] | None = None,
        upper: Float[Tensor, " 3"] | None = None,
    ) -> None:
        """Replace the factors by resampled ones covering ``[lower, upper]`` (grid coordinates).

        Upsampling (same box, more nodes) and box shrinking (a sub-box) are both resampling. The
        parameters are replaced, so the optimizer must be rebuilt afterwards.
        """
        device = self.planes[0].device
        lower = torch.full((3,), -1.0, device=device) if lower is None else lower
        upper = torch.full((3,), 1.0, device=device) if upper is None else upper
        axes = [torch.linspace(float(lower[i]), float(upper[i]), resolution[i], device=device) for i in range(3)]
        for i, ((a, b), c) in enumerate(MODES):
            gy, gx = torch.meshgrid(axes[b], axes[a], indexing="ij")
            pts = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)  # [hb * wa, 2]
            new_plane = sample_plane(self.planes[i].data, pts).t().reshape(-1, resolution[b], resolution[a])
            new_line = interpolate_lines(self.lines[i].data, axes[c]).t()
            self.planes[i] = nn.Parameter(new_plane.contiguous())
            self.lines[i] = nn.Parameter(new_line.contiguous())
