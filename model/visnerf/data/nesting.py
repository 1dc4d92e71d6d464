"""Whether a parameter axis sweeps nested shapes: the visual hulls of its settings, from the images.

The isosurfaces of one scalar field at increasing isovalues are nested: each lies inside the one
before it (or around it, when the inside is below the isovalue). A visual hull is monotone in what
it carves from (an object inside another has its hull inside the other's, seen by the same
cameras), so nested surfaces give nested hulls. A timestep series, a transfer-function sweep or a
simulation parameter moves, splits and recolours its content and does not.

``axis_nesting`` carves each setting's hull (``data.carving``) and measures, for every pair of
neighbouring values of one axis (the other axes held), the share of each hull that lies outside
the other; an axis is nested when, in one direction, that share stays within a tolerance for every
pair, while the hulls do change along it. The carving costs about 0.4 s a setting at 64^3 cells
(tangle_iso, 5 settings of 42 views at 128x128: 1.9 s).
"""

from dataclasses import dataclass

import torch
from jaxtyping import Bool
from torch import Tensor

from visnerf.data.carving import carve_occupancy, setting_groups
from visnerf.data.scene import SceneData


@dataclass(frozen=True)
class AxisNesting:
    """How the hulls of one axis's neighbouring values contain each other."""

    axis: int
    pairs: int
    """Neighbouring pairs measured (over every combination of the other axes)."""
    outside_shrinking: float
    """Largest share of the hull at the higher value lying outside the hull at the lower one (0:
    the hulls shrink as the value grows)."""
    outside_growing: float
    """Largest share of the hull at the lower value lying outside the hull at the higher one (0:
    the hulls grow with the value)."""
    change: float
    """Largest share of a pair's union that is not in both hulls (0: the axis changes no hull)."""

    def nested(self, tolerance: float) -> bool:
        """Nested one way within ``tolerance`` for every pair, and the hulls change by more than it."""
        return (self.pairs > 0 and self.change > tolerance
                and min(self.outside_shrinking, self.outside_growing) <= tolerance)

    @property
    def shrinking(self) -> bool:
        """The hulls shrink as the value grows (the isovalue's inside is above it)."""
        return self.outside_shrinking <= self.outside_growing


def setting_hulls(
    scene: SceneData, box: Tensor, resolution: int, tolerance: int, min_seen_fraction: float
) -> tuple[Tensor, list[Bool[Tensor, " m"]]]:
    """(settings ``[s, k]``, each setting's visual hull flattened over ``resolution^3`` cells of ``box``)."""
    settings, hulls = [], []
    for frames in setting_groups(scene.params):
        hull = carve_occupancy(scene.subset(frames), box, (resolution,) * 3, tolerance,
                               min_seen_fraction=min_seen_fraction)
        settings.append(scene.params[frames[0]].float())
        hulls.append(hull.reshape(-1))
    return torch.stack(settings), hulls


def _share_outside(a: Bool[Tensor, " m"], b: Bool[Tensor, " m"]) -> float:
    """Share of ``a``'s cells outside ``b`` (0 for an empty ``a``)."""
    count = int(a.sum())
    return 0.0 if count == 0 else int((a & ~b).sum()) / count


def axis_nesting(settings: Tensor, hulls: list[Bool[Tensor, " m"]], axis: int) -> AxisNesting:
    """Nesting of the hulls along ``axis`` (``settings [s, k]`` and ``hulls`` from ``setting_hulls``)."""
    others = torch.cat([settings[:, :axis], settings[:, axis + 1:]], dim=1)  # [s, k-1]
    keys = [tuple(row.tolist()) for row in others]
    pairs, shrink, grow, change = 0, 0.0, 0.0, 0.0
    for key in sorted(set(keys)):
        members = sorted((float(settings[i, axis]), i) for i, k in enumerate(keys) if k == key)
        for (_, lo), (_, hi) in zip(members[:-1], members[1:], strict=True):
            a, b = hulls[lo], hulls[hi]
            pairs += 1
            shrink = max(shrink, _share_outside(b, a))
            grow = max(grow, _share_outside(a, b))
            change = max(change, _share_outside(a | b, a & b))
    return AxisNesting(axis, pairs, shrink, grow, change)


def nested_axis(
    scene: SceneData, box: Tensor, resolution: int, tolerance: int, min_seen_fraction: float, nest_tolerance: float
) -> tuple[int, list[AxisNesting]]:
    """The first axis whose settings' hulls are nested (``AxisNesting.nested``), or -1, with every
    axis's measurement (none for K = 0 or a single setting)."""
    if scene.n_params == 0:
        return -1, []
    settings, hulls = setting_hulls(scene, box, resolution, tolerance, min_seen_fraction)
    found = [axis_nesting(settings, hulls, k) for k in range(scene.n_params)]
    chosen = next((n.axis for n in found if n.nested(nest_tolerance)), -1)
    return chosen, found


def describe(n: AxisNesting) -> str:
    """One line for the recipe's reason."""
    direction = "shrink" if n.shrinking else "grow"
    outside = min(n.outside_shrinking, n.outside_growing)
    other = max(n.outside_shrinking, n.outside_growing)
    return (f"axis {n.axis}: over {n.pairs} neighbouring pairs the hulls {direction} with the value, at most "
            f"{100 * outside:.2f} % of one outside the other (the other way {100 * other:.1f} %), changing by up to "
            f"{100 * n.change:.1f} %")

