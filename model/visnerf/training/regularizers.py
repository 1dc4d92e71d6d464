"""Priors on the factors: L1 sparsity, L1 pull of parameter vectors toward 1, total variation."""

from dataclasses import dataclass

import torch
from torch import Tensor

from visnerf.representation.field import VisNerfField


@dataclass(frozen=True)
class RegularizerWeights:
    l1_density: float
    param_l1: float
    tv_density: float
    tv_appearance: float
    tv_params: float


def regularization(field: VisNerfField, w: RegularizerWeights) -> dict[str, Tensor]:
    """Each weighted term (only the non-zero ones are computed)."""
    terms: dict[str, Tensor] = {}
    if w.l1_density > 0:
        terms["l1"] = w.l1_density * field.density_grid.l1()
    if w.param_l1 > 0 and field.cfg.n_params > 0:
        terms["param_l1"] = w.param_l1 * (field.density_params.l1_to_one() + field.appearance_params.l1_to_one())
    if w.tv_density > 0:
        terms["tv_density"] = w.tv_density * field.density_grid.total_variation()
    if w.tv_appearance > 0:
        terms["tv_appearance"] = w.tv_appearance * field.appearance_grid.total_variation()
    if w.tv_params > 0 and field.cfg.n_params > 0:
        terms["tv_params"] = w.tv_params * (
            field.density_params.total_variation() + field.appearance_params.total_variation()
        )
    return {k: v.to(field.device) if isinstance(v, Tensor) else torch.tensor(v) for k, v in terms.items()}
