"""LPIPS, only where the ``lpips`` package and locally stored backbone weights are present.

Nothing is downloaded: the backbone (a torchvision-style state dict, e.g. AlexNet's
``features.N.weight`` tensors) comes from a file the caller names; the small linear calibration
layers ship inside the ``lpips`` package itself. When anything is missing, ``load_lpips`` returns no
scorer and the reason, and the report says LPIPS was not computed.
"""

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from jaxtyping import Float

LpipsNet = Literal["alex", "vgg", "squeeze"]
ImagePair = Callable[[np.ndarray, np.ndarray], float]


@dataclass(frozen=True)
class LpipsConfig:
    """Where LPIPS gets its weights."""

    weights: Path | None = None
    """Backbone weights file (torchvision state dict of the ``net``); None: LPIPS is not computed."""
    net: LpipsNet = "alex"
    """Backbone network (the paper's LPIPS figures use AlexNet)."""


@dataclass(frozen=True)
class LpipsScorer:
    """A loaded LPIPS network; call it with two [h, w, 3] images in [0, 1]."""

    network: torch.nn.Module
    device: torch.device
    description: str

    @torch.inference_mode()
    def __call__(self, a: Float[np.ndarray, "h w 3"], b: Float[np.ndarray, "h w 3"]) -> float:
        def to_tensor(img: np.ndarray) -> torch.Tensor:
            t = torch.as_tensor(np.ascontiguousarray(img), dtype=torch.float32, device=self.device)
            return t.permute(2, 0, 1)[None] * 2.0 - 1.0  # [1, 3, h, w] in [-1, 1]

        return float(self.network(to_tensor(a), to_tensor(b)).reshape(-1)[0])


def _map_backbone(network: torch.nn.Module, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """torchvision ``features.N.*`` keys -> the LPIPS module's ``net.sliceK.N.*`` keys."""
    if any(k.startswith("net.") for k in state):
        return {k: v for k, v in state.items() if k.startswith("net.")}
    slot = {}
    for slice_name, block in network.net.named_children():  # type: ignore[union-attr]
        for index, _ in block.named_children():
            slot[index] = slice_name
    mapped = {}
    for key, value in state.items():
        parts = key.split(".")
        if len(parts) == 3 and parts[0] == "features" and parts[1] in slot:
            mapped[f"net.{slot[parts[1]]}.{parts[1]}.{parts[2]}"] = value
    return mapped


def load_lpips(cfg: LpipsConfig, device: torch.device) -> tuple[LpipsScorer | None, str]:
    """(scorer, description) or (None, why LPIPS is not computed). Never downloads anything."""
    if cfg.weights is None:
        return None, "no backbone weights given (--lpips-weights PATH); LPIPS needs them stored locally"
    if not cfg.weights.is_file():
        return None, f"backbone weights file {cfg.weights} does not exist"
    try:
        lpips = importlib.import_module("lpips")
    except ImportError as exc:
        return None, f"the lpips package is not importable ({exc})"
    try:
        network = lpips.LPIPS(net=cfg.net, pretrained=True, pnet_rand=True, verbose=False)
        state = torch.load(cfg.weights, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            return None, f"{cfg.weights} is not a state dict"
        mapped = _map_backbone(network, state)
        expected = {k for k in network.state_dict() if k.startswith("net.")}
        missing = sorted(expected - set(mapped))
        if missing:
            return None, f"{cfg.weights} lacks backbone tensors for {cfg.net} (first missing: {missing[0]})"
        network.load_state_dict(mapped, strict=False)
    except (OSError, RuntimeError, ValueError, KeyError) as exc:
        return None, f"LPIPS could not be set up from {cfg.weights}: {exc}"
    scorer = LpipsScorer(network.to(device).eval(), device, f"LPIPS ({cfg.net}, backbone {cfg.weights.name})")
    return scorer, scorer.description
