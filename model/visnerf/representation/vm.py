"""Vector-matrix (VM) factorisation of a 3-D feature grid (TensoRF).

Three planes (XY, XZ, YZ) times three lines (Z, Y, X). Grid coordinates are in [-1, 1] with
``align_corners=True``: -1 and +1 are the centres of the first and last grid nodes. Features of
the three modes are concatenated: ``[n, 3 * n_components]``.

``VMGrid.sample`` reads the factors as row tables through ``embedding_bag`` (differentiable in the
factors, not the coordinates: samples sit at fixed positions). Its backward is one sparse-dense
product per table on the CPU (``vm_taps.weighted_row_sum``). ``grid_sample`` and advanced
indexing, its slow reference twin ``VMGrid._sample``, back-propagate through
``grid_sampler_2d_backward`` and ``index_put_(accumulate=True)``, which took 46 % of a Nyx
training step on the CPU.
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


def factor_tables(planes: list[Tensor], lines: list[Tensor]) -> tuple[Float[Tensor, "p c"], Float[Tensor, "l c"]]:
    """Planes ``[c, h, w]`` and lines ``[c, r]`` (in ``MODES`` order) stacked as the row tables of
    ``TapLayout``: plane row ``y * w + x`` holds node ``(x, y)``, line row ``z`` node ``z``."""
    plane_table = torch.cat([p.permute(1, 2, 0).reshape(-1, p.shape[0]) for p in planes])
    return plane_table, torch.cat([line.t() for line in lines]).contiguous()


class VMGrid(nn.Module):
    """Planes and lines of one VM grid; ``sample(coords) -> [n, 3 * n_components]``.

    The factors are held as the two row tables that ``sample`` reads (``plane_table`` and
    ``line_table``, the layout of ``TapLayout``), so neither training nor inference copies them
    per lookup, and the lookups' gradients land in the parameters as they are. ``planes`` and
    ``lines`` are views of the tables in the ``[c, h, w]`` and ``[c, r]`` layout of a TensoRF
    grid, which is also how they are stored in a state dict (and a checkpoint).
    """

    def __init__(self, n_components: int, resolution: tuple[int, int, int], init_scale: float) -> None:
        super().__init__()
        self.n_components = n_components
        planes, lines = [], []
        for (a, b), c in MODES:
            planes.append(init_scale * torch.randn(n_components, resolution[b], resolution[a]))
            lines.append(init_scale * torch.randn(n_components, resolution[c]))
        self._set_factors(planes, lines)
        self.register_state_dict_post_hook(_factors_to_state_dict)
        self.register_load_state_dict_pre_hook(_factors_from_state_dict)

    def _set_factors(self, planes: list[Tensor], lines: list[Tensor]) -> None:
        """Replace the factors by ``planes`` ([c, h, w] each, in ``MODES`` order) and ``lines``
        ([c, r] each): new parameters, so an optimizer must be rebuilt."""
        self._plane_shapes = tuple((p.shape[1], p.shape[2]) for p in planes)
        self._line_lengths = tuple(line.shape[1] for line in lines)
        plane_table, line_table = factor_tables(planes, lines)
        self.plane_table, self.line_table = nn.Parameter(plane_table), nn.Parameter(line_table)

    def row_views(self, plane_rows: Tensor, line_rows: Tensor) -> tuple[list[Tensor], list[Tensor]]:
        """Views of tensors laid out as ``row_tables()`` (the tables, or their gradients): each
        plane's rows as ``[h, w, c]`` and each line's as ``[r, c]``, in ``MODES`` order."""
        planes, start = [], 0
        for h, w in self._plane_shapes:
            planes.append(plane_rows[start : start + h * w].view(h, w, -1))
            start += h * w
        lines, start = [], 0
        for r in self._line_lengths:
            lines.append(line_rows[start : start + r])
            start += r
        return planes, lines

    @property
    def planes(self) -> list[Tensor]:
        """The three planes, ``[c, h, w]`` each, as views of ``plane_table`` (writing into them writes
        the table)."""
        return [rows.permute(2, 0, 1) for rows in self.row_views(*self.row_tables())[0]]

    @property
    def lines(self) -> list[Tensor]:
        """The three lines, ``[c, r]`` each, as views of ``line_table``."""
        return [rows.t() for rows in self.row_views(*self.row_tables())[1]]

    @property
    def resolution(self) -> tuple[int, int, int]:
        res = [0, 0, 0]
        for ((a, b), c), (h, w), r in zip(MODES, self._plane_shapes, self._line_lengths, strict=True):
            res[a], res[b], res[c] = w, h, r
        return (res[0], res[1], res[2])

    def row_tables(self) -> tuple[Float[Tensor, "p c"], Float[Tensor, "l c"]]:
        """The three planes stacked as rows ``[sum h * w, c]`` and the three lines as ``[sum r, c]``
        (the layout of ``TapLayout``): the parameters themselves."""
        return self.plane_table, self.line_table

    def tap_layout(self) -> TapLayout:
        """Tap layout of the current resolution (cached; resampling changes it)."""
        layout = getattr(self, "_layout", None)
        device = self.plane_table.device
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
        """Mean absolute value of planes and lines (sparsity prior), each factor weighted alike."""
        total = sum(p.abs().mean() for p in self.planes) + sum(line.abs().mean() for line in self.lines)
        return total / (2 * len(MODES))

    def total_variation(self) -> Tensor:
        """Mean squared difference of neighbouring entries of planes and lines."""
        total = torch.zeros((), device=self.plane_table.device)
        for plane, line in zip(self.planes, self.lines, strict=True):
            rows = plane.permute(1, 2, 0)  # [h, w, c], contiguous: the table's own layout
            total = total + (rows[1:] - rows[:-1]).pow(2).mean()
            total = total + (rows[:, 1:] - rows[:, :-1]).pow(2).mean()
            total = total + (line[:, 1:] - line[:, :-1]).pow(2).mean()
        return total / len(MODES)

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
        device = self.plane_table.device
        lower = torch.full((3,), -1.0, device=device) if lower is None else lower
        upper = torch.full((3,), 1.0, device=device) if upper is None else upper
        axes = [torch.linspace(float(lower[i]), float(upper[i]), resolution[i], device=device) for i in range(3)]
        planes, lines = [], []
        for ((a, b), c), plane, line in zip(MODES, self.planes, self.lines, strict=True):
            gy, gx = torch.meshgrid(axes[b], axes[a], indexing="ij")
            pts = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1)  # [hb * wa, 2]
            planes.append(sample_plane(plane.detach(), pts).t().reshape(-1, resolution[b], resolution[a]))
            lines.append(interpolate_lines(line.detach(), axes[c]).t())
        self._set_factors(planes, lines)


def _factors_to_state_dict(module: VMGrid, state: dict, prefix: str, _meta: object) -> None:
    """State-dict hook: the tables leave as ``planes.i`` ``[c, h, w]`` and ``lines.i`` ``[c, r]``."""
    del state[prefix + "plane_table"], state[prefix + "line_table"]
    for i, (plane, line) in enumerate(zip(module.planes, module.lines, strict=True)):
        state[f"{prefix}planes.{i}"] = plane.detach().contiguous()
        state[f"{prefix}lines.{i}"] = line.detach().contiguous()


def _factors_from_state_dict(module: VMGrid, state: dict, prefix: str, *_: object) -> None:
    """Load pre-hook: ``planes.i`` and ``lines.i``, of the module's shapes, become the tables."""
    names = [f"{prefix}{kind}.{i}" for kind in ("planes", "lines") for i in range(len(MODES))]
    if not all(n in state for n in names):
        return  # load_state_dict reports the missing table entries
    planes = [state.pop(f"{prefix}planes.{i}") for i in range(len(MODES))]
    lines = [state.pop(f"{prefix}lines.{i}") for i in range(len(MODES))]
    for name, given, own in zip(names, planes + lines, module.planes + module.lines, strict=True):
        if given.shape != own.shape:
            raise RuntimeError(f"size mismatch for {name}: copying a param with shape {list(given.shape)}, "
                               f"the module has {list(own.shape)}")
    state[prefix + "plane_table"], state[prefix + "line_table"] = factor_tables(planes, lines)
