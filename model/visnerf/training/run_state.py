"""The run-state file: everything a killed training run needs to go on where it stopped.

A checkpoint holds a model; a run state holds a run: the field's tensors in float32 (no storage
coding: a resumed run must continue from exactly the values it had), the optimizer's moments, the
weight average, the random generators, the carved hull and occupancy, and, in the JSON document,
the schedule's position, the configurations, the log and a fingerprint of the training frames.
``visnerf train`` writes it beside ``--out`` (``M.safetensors`` -> ``M.resume``) every
``TrainConfig.checkpoint_every_s`` seconds of training and when it is stopped (SIGTERM, Ctrl-C),
always atomically (``checkpoint.write_atomically``): a process killed at any instant leaves the
previous state or the new one. The file is deleted once the run has written its checkpoint.

Format: a safetensors file (tensors only, nothing executable) whose metadata holds the JSON
document under ``visnerf_run_state``; reading checks the format version and that every floating
tensor is finite, and raises ``RunStateError`` naming the problem otherwise.
"""

import hashlib
import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save as save_safetensors_bytes
from torch import Tensor

from visnerf.checkpoint import V1_TRAIN_DROPPED, CheckpointError, read_safetensors_header, write_atomically
from visnerf.data.scene import SceneData

RUN_STATE_KEY = "visnerf_run_state"
RUN_STATE_VERSION = 2
RUN_STATE_SUFFIX = ".resume"
_MAX_HEADER_BYTES = 64 * 1024 * 1024
"""Longest JSON header read: the document holds the run's whole log."""


class RunStateError(ValueError):
    """A run-state file could not be used; the message names the problem."""


def run_state_path(out: str | Path) -> Path:
    """Where a run writing checkpoint ``out`` keeps its run state (``M.safetensors`` -> ``M.resume``)."""
    return Path(out).with_suffix(RUN_STATE_SUFFIX)


def scene_fingerprint(scene: SceneData) -> str:
    """A digest of what the run state refers to: frame count, image size and focal length, every
    camera pose and every parameter value (not the pixels: hashing every image would cost more than it
    guards). A resumed run refuses frames with another fingerprint."""
    h = hashlib.sha256()
    k = scene.intrinsics
    h.update(json.dumps([scene.n_frames, k.width, k.height, float(k.fx), float(k.fy)]).encode())
    h.update(scene.c2w.detach().cpu().to(torch.float32).contiguous().numpy().tobytes())
    h.update(scene.params.detach().cpu().to(torch.float64).contiguous().numpy().tobytes())
    h.update(json.dumps([a.name for a in scene.param_axes]).encode())
    return h.hexdigest()[:32]


def write_run_state(path: str | Path, tensors: dict[str, Tensor], document: dict[str, Any]) -> Path:
    """Write the run state atomically; ``document`` must be JSON without NaN."""
    blob = save_safetensors_bytes(
        {name: t.detach().cpu().contiguous() for name, t in tensors.items()},
        metadata={RUN_STATE_KEY: json.dumps({"format_version": RUN_STATE_VERSION, **document}, allow_nan=False)},
    )
    return write_atomically(path, blob)


def read_run_state(path: str | Path) -> tuple[dict[str, Any], dict[str, Tensor]]:
    """(document, CPU tensors) of a run-state file, checked; ``RunStateError`` otherwise."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise RunStateError(f"cannot read run state {path}: {exc.strerror}") from None
    try:
        header = read_safetensors_header(blob, _MAX_HEADER_BYTES)
    except CheckpointError as exc:
        raise RunStateError(f"{path} is not a run state ({exc})") from None
    try:
        document = json.loads((header.get("__metadata__") or {})[RUN_STATE_KEY])
    except (json.JSONDecodeError, KeyError, AttributeError, TypeError):
        raise RunStateError(f"{path} is not a run state of visnerf train (no {RUN_STATE_KEY!r} document)") from None
    version = document.get("format_version") if isinstance(document, dict) else None
    if version == 1:
        document = migrate_run_state(document)
    elif version != RUN_STATE_VERSION:
        raise RunStateError(f"{path}: unsupported run-state version {version!r} (this build reads {RUN_STATE_VERSION})")
    try:
        tensors = load_safetensors_bytes(blob)
    except Exception as exc:  # safetensors raises its own error types for truncation / corruption
        raise RunStateError(f"{path}: run-state data is corrupt or truncated: {exc}") from None
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise RunStateError(f"{path}: tensor {name!r} holds non-finite values")
    return document, tensors


def migrate_run_state(document: dict[str, Any]) -> dict[str, Any]:
    """A version 1 document as version 2 writes it (a copy): the training settings that are gone
    (``checkpoint.V1_TRAIN_DROPPED``) left out of its configuration."""
    out = dict(document)
    if isinstance(document.get("train"), dict):
        out["train"] = {k: v for k, v in document["train"].items() if k not in V1_TRAIN_DROPPED}
    out["format_version"] = RUN_STATE_VERSION
    return out


def pack_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """An optimizer's state as tensors ``optimizer.<param index>.<key>`` and its groups as JSON."""
    state = optimizer.state_dict()
    tensors = {f"optimizer.{i}.{key}": value for i, entry in state["state"].items()
               for key, value in entry.items() if isinstance(value, Tensor)}
    scalars = {str(i): {key: value for key, value in entry.items() if not isinstance(value, Tensor)}
               for i, entry in state["state"].items()}
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def unpack_optimizer(optimizer: torch.optim.Optimizer, tensors: dict[str, Tensor], packed: dict[str, Any]) -> None:
    """Load ``pack_optimizer``'s output into ``optimizer`` (built over the same parameters)."""
    per_param: dict[int, dict[str, Any]] = {int(i): dict(values) for i, values in packed["scalars"].items()}
    for name, value in tensors.items():
        if name.startswith("optimizer."):
            _, index, key = name.split(".", 2)
            per_param.setdefault(int(index), {})[key] = value
    groups = packed["param_groups"]
    for group in groups:
        if "betas" in group:
            group["betas"] = tuple(group["betas"])
    n_params = sum(len(g["params"]) for g in optimizer.param_groups)
    if sum(len(g["params"]) for g in groups) != n_params:
        raise RunStateError(f"the run state's optimizer covers {sum(len(g['params']) for g in groups)} "
                            f"parameters, the field has {n_params}")
    optimizer.load_state_dict({"state": per_param, "param_groups": groups})
