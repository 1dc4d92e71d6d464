"""The field at one fixed parameter tuple, with the frame-constant work done once (inference).

Within a frame every sample shares the same parameter features ``q``. The field scales spatial
channel ``i`` by ``q[i % c]``, appends ``q`` and then applies the decoder's first linear layer, so
both steps fold into that layer: the spatial columns of its weight are scaled by ``q`` once and the
``q`` columns become part of the bias. The colour decoder's view-direction columns depend only on
the ray, so their product is taken once per ray instead of once per sample. What is left per
sample is the VM lookup and the matrix products, one per VM mode; no ``[m, f]`` repeat,
product or concatenation.
The result equals ``VisNerfField.density`` / ``color`` up to float rounding (tested).
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor

from visnerf.representation.decoders import Decoder, encode_position, encode_sh
from visnerf.representation.field import VisNerfField


@dataclass(frozen=True)
class FoldedLayer:
    """First decoder layer with the parameter features folded in."""

    mode_weights_t: tuple[Float[Tensor, "c h"], ...]
    """Spatial columns of each VM mode, scaled by the parameter features, transposed for ``x @ w``."""
    rest_weight_t: Float[Tensor, "e h"]
    """Columns of the trailing encoding (positional or spherical harmonics), transposed."""
    bias: Float[Tensor, " h"]
    """Layer bias plus the product of the ``q`` columns with ``q``."""


def fold_first_layer(decoder: Decoder, q: Float[Tensor, " c"], n_components: int) -> FoldedLayer:
    """Fold parameter features ``q`` into ``decoder.hidden``.

    The layer's input is ``[spatial * q_rep, q, rest]`` with ``spatial`` the three VM modes of
    ``n_components`` channels each, concatenated.
    """
    w, b = decoder.hidden.weight, decoder.hidden.bias  # [h, n_in], [h]
    c = q.shape[0]
    n_spatial = 3 * n_components
    scaled = w[:, :n_spatial] * q.repeat(n_spatial // c)[None]  # [h, f]
    return FoldedLayer(
        mode_weights_t=tuple(scaled[:, i * n_components:(i + 1) * n_components].t().contiguous() for i in range(3)),
        rest_weight_t=w[:, n_spatial + c:].t().contiguous(),
        bias=b + w[:, n_spatial:n_spatial + c] @ q,
    )


class FrameField:
    """Density and colour of ``field`` at parameter features (q_density, q_appearance), no grad."""

    def __init__(
        self, field: VisNerfField, q_density: Float[Tensor, "1 c"], q_appearance: Float[Tensor, "1 c"]
    ) -> None:
        self.field = field
        cfg = field.cfg
        self.density_layer = fold_first_layer(field.density_decoder, q_density[0], cfg.n_density_components)
        self.color_layer = fold_first_layer(field.color_decoder, q_appearance[0], cfg.n_appearance_components)

    def density(self, points: Float[Tensor, "m 3"]) -> Float[Tensor, " m"]:
        f = self.field
        coords = f.to_grid(points)
        layer = self.density_layer
        hidden = torch.addmm(layer.bias, encode_position(coords, f.cfg.pos_encoding_freqs), layer.rest_weight_t)
        for feat, w_t in zip(f.density_grid.sample_modes(coords), layer.mode_weights_t, strict=True):
            hidden.addmm_(feat.t(), w_t)  # [m, h]; the transposed view is read in place by the GEMM
        raw = F.linear(hidden.relu_(), f.density_decoder.out.weight, f.density_decoder.out.bias)[:, 0]
        return F.softplus(raw + f.cfg.density_shift)

    def direction_terms(self, directions: Float[Tensor, "a 3"]) -> Float[Tensor, "a h"]:
        """Per-ray part of the colour decoder's first layer (bias included)."""
        sh = encode_sh(directions, self.field.cfg.sh_degree)
        return torch.addmm(self.color_layer.bias, sh, self.color_layer.rest_weight_t)

    def color(
        self, points: Float[Tensor, "m 3"], ray_terms: Float[Tensor, "m h"]
    ) -> Float[Tensor, "m 3"]:
        """RGB at ``points``; ``ray_terms`` is ``direction_terms`` of each sample's ray."""
        f = self.field
        hidden = ray_terms.clone()  # [m, h]
        for feat, w_t in zip(f.appearance_grid.sample_modes(f.to_grid(points)), self.color_layer.mode_weights_t,
                             strict=True):
            hidden.addmm_(feat.t(), w_t)
        raw = F.linear(hidden.relu_(), f.color_decoder.out.weight, f.color_decoder.out.bias)
        return torch.sigmoid(raw)
