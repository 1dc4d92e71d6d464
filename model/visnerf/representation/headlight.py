"""A colour that every surface point shares as a function of the angle between its normal and the
view: the highlight of a light at the camera (a headlight, as isosurface renderers light by default).

Blinn-Phong under a headlight adds ``specular * cos^shininess`` of the angle between the normal and
the view, the same at every point of the surface. A colour decoder that reads that cosine among its
features may still learn the highlight point by point, and each point of a sparse set of views is
seen near its highlight's angle by few views or none; in a new view its highlight is then missing
or misplaced. This table is one function of the angle for the whole scene, learnt from every point
that any view sees, so a point shows its highlight from wherever its normal faces the camera.

The table holds ``bins`` knots uniform in the angle (0 to 180 degrees, linear between them), which
resolves a narrow lobe (a Blinn-Phong exponent of 40 falls to half its height at 10.6 degrees)
where knots uniform in the cosine would be coarse near 0 degrees.
"""

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn


class HeadlightTable(nn.Module):
    """RGB added to the decoded colour, tabulated over the angle between normal and view.

    Parameter ``table`` [bins, 3], zeros at the start (no effect)."""

    def __init__(self, bins: int) -> None:
        super().__init__()
        if bins < 2:
            raise ValueError(f"a headlight table needs at least 2 bins, got {bins}")
        self.table = nn.Parameter(torch.zeros(bins, 3))

    @property
    def bins(self) -> int:
        return self.table.shape[0]

    def forward(self, cosines: Float[Tensor, "n 1"]) -> Float[Tensor, "n 3"]:
        """The table at the angles ``acos(cosines)`` (clamped to [-1, 1]), linear between knots;
        float32 whatever the table's dtype. No gradient flows into ``cosines``."""
        angle = torch.acos(cosines.detach().float().clamp(-1.0, 1.0))[:, 0]  # [n], radians
        position = angle * ((self.bins - 1) / math.pi)  # [n] in [0, bins - 1]
        lower = position.floor().clamp(max=self.bins - 2)
        frac = (position - lower)[:, None]  # [n, 1] in [0, 1]
        index = lower.long()
        table = self.table.float()
        return table.index_select(0, index) * (1.0 - frac) + table.index_select(0, index + 1) * frac
