"""Checkpoints: one ``.safetensors`` file, tensors only, with a JSON document under ``visnerf``.

Loading validates everything before building a model: the container, the format version, the
metadata (``meta_checks``: finite numbers, parameter axes, box, camera, background, kind), the
configuration, every tensor's presence, shape and dtype, and that all values are finite. Any
problem raises ``CheckpointError`` with a message that names it. Saving is atomic.
"""

import bisect
import json
import os
import struct
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from safetensors.torch import load as load_safetensors_bytes
from safetensors.torch import save as save_safetensors_bytes

from visnerf.config import FACTOR_STORAGE_DTYPES, FieldConfig, RenderConfig
from visnerf.factor_codec import ROW_SCALE_SUFFIX, decode_rows, encode_rows
from visnerf.meta_checks import MetadataError, check_metadata, parse_metadata_json
from visnerf.provenance import Provenance, ProvenanceError
from visnerf.representation.field import VisNerfField

FORMAT_VERSION = 2
"""Version 2 (2026-12-04): every configuration field is written, and reading refuses a key it does
not know. Version 1 documents are migrated on reading (``migrate``)."""
METADATA_KEY = "visnerf"
_MAX_HEADER_BYTES = 16 * 1024 * 1024


class CheckpointError(ValueError):
    """A checkpoint could not be read; the message names the problem."""


@dataclass(frozen=True)
class ParamAxis:
    """One parameter axis: its name, training range and the distinct training values."""

    name: str
    min: float
    max: float
    values: tuple[float, ...]
    default: float

    def _rounding(self) -> float:
        """The widest rounding a float32 read-back of a value of this axis may carry."""
        return 1e-6 * max(abs(self.min), abs(self.max), self.max - self.min, 1e-30)

    def contains(self, value: float) -> bool:
        """Whether ``value`` lies in [min, max], allowing the rounding of a float32 at this
        magnitude (0.12 read back from float32 is 0.1199999973: the end of the range, not outside)."""
        tol = self._rounding()
        return self.min - tol <= value <= self.max + tol

    def training_value(self, value: float) -> float:
        """The training value ``value`` is a float32 rounding of (the nearest within that
        rounding; the values increase strictly), else ``value`` itself."""
        at = bisect.bisect_left(self.values, value)
        near = [v for v in self.values[max(0, at - 1):at + 1] if abs(v - value) <= self._rounding()]
        return min(near, key=lambda v: abs(v - value)) if near else value

    def normalize(self, value: float) -> float:
        """Map [min, max] to [-1, 1]; a float32 rounding of a training value maps exactly where
        that value does, so frames read back from float32 sit on the field's knots."""
        span = self.max - self.min
        return 0.0 if span <= 0 else 2.0 * (self.training_value(value) - self.min) / span - 1.0


@dataclass(frozen=True)
class CheckpointMeta:
    """The JSON document stored in the checkpoint header."""

    field: FieldConfig
    render: RenderConfig
    param_axes: tuple[ParamAxis, ...]
    bbox: tuple[tuple[float, float, float], tuple[float, float, float]]
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    camera: dict[str, float] = field(default_factory=dict)
    image_width: int = 0
    image_height: int = 0
    title: str = ""
    kind: Literal["dvr", "ir"] = "dvr"
    occupancy_resolution: tuple[int, int, int] | None = None
    provenance: Provenance = field(default_factory=Provenance)
    format_version: int = FORMAT_VERSION

    def to_json(self) -> str:
        data = asdict(self)
        data["field"] = self.field.to_dict()
        data["render"] = self.render.to_dict()
        data["provenance"] = self.provenance.to_dict()
        return json.dumps(data, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> "CheckpointMeta":
        """Parse and check the metadata (``meta_checks``, then the configurations' own checks):
        ``CheckpointError`` names the field of the first problem, before anything is built."""
        try:
            data = parse_metadata_json(text)
        except MetadataError as exc:
            raise CheckpointError(f"checkpoint metadata: {exc}") from None
        if not isinstance(data, dict):
            raise CheckpointError("checkpoint metadata is not a JSON object")
        data = migrate(data)
        version = data.get("format_version")
        if version != FORMAT_VERSION:
            raise CheckpointError(
                f"unsupported checkpoint format version {version!r} (this build reads {FORMAT_VERSION})"
            )
        try:
            check_metadata(data)
        except MetadataError as exc:
            raise CheckpointError(f"checkpoint metadata: {exc}") from None
        field_cfg = _config_from(FieldConfig, data["field"], "field")
        try:
            provenance = Provenance.from_dict(data.get("provenance", {}))
        except ProvenanceError as exc:
            raise CheckpointError(f"checkpoint metadata: {exc}") from None
        render_cfg = _config_from(RenderConfig, data.get("render", {}), "render")
        try:
            axes = tuple(
                ParamAxis(str(a["name"]), float(a["min"]), float(a["max"]),
                          tuple(float(v) for v in a["values"]), float(a["default"]))
                for a in data["param_axes"]
            )
            occ = data.get("occupancy_resolution")
            meta = cls(
                field=field_cfg,
                render=render_cfg,
                param_axes=axes,
                bbox=tuple(tuple(float(x) for x in corner) for corner in data["bbox"]),  # type: ignore[arg-type]
                background=tuple(float(x) for x in data.get("background", (1.0, 1.0, 1.0))),  # type: ignore[arg-type]
                camera={k: float(v) for k, v in data.get("camera", {}).items()},
                image_width=int(data["image_width"]),
                image_height=int(data["image_height"]),
                title=str(data.get("title", "")),
                kind=str(data.get("kind", "dvr")),
                occupancy_resolution=None if occ is None else tuple(int(r) for r in occ),  # type: ignore[arg-type]
                provenance=provenance,
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"checkpoint metadata is incomplete or malformed: {exc!r}") from None
        if len(meta.param_axes) != meta.field.n_params:
            raise CheckpointError(
                f"metadata names {len(meta.param_axes)} parameter axes but the field has {meta.field.n_params}"
            )
        for axis, length in zip(meta.param_axes, meta.field.param_lengths, strict=True):
            if len(axis.values) != length:
                raise CheckpointError(f"axis {axis.name!r} lists {len(axis.values)} values, the field {length}")
        return meta


V1_FIELD_DEFAULTS = {"factor_storage": "float32", "level_cosine_powers": []}
"""What a version 1 checkpoint meant by leaving out a field option added later: float32 factors, the
level field's cosine alone (not the defaults of a new field)."""
V1_RENDER_DROPPED = ("full_weight_threshold", "chunk_rays")
"""Version 1 render keys that are not read: ``full_weight_threshold`` was a weight per sample at
whatever spacing (read as one per voxel it would be another threshold at every spacing; the per-voxel
default applies), ``chunk_rays`` belongs to the machine, not the model."""


V1_TRAIN_DROPPED = ("random_background",)
"""Training settings a version 1 run recorded that are gone: random backgrounds were measured and
not kept (docs/trials.md), and every run recorded it off."""


def migrate(data: dict[str, Any]) -> dict[str, Any]:
    """A metadata document of an older format as the current format writes it (a copy); the current
    format and anything else are returned as they are (``from_json`` refuses an unknown version)."""
    if data.get("format_version") != 1:
        return data
    out = dict(data)
    if isinstance(data.get("field"), dict):
        out["field"] = {**V1_FIELD_DEFAULTS, **data["field"]}
    if isinstance(data.get("render"), dict):
        out["render"] = {k: v for k, v in data["render"].items() if k not in V1_RENDER_DROPPED}
    provenance = data.get("provenance")
    if isinstance(provenance, dict) and isinstance(provenance.get("recipe"), dict):
        recipe = {k: v for k, v in provenance["recipe"].items() if k not in V1_TRAIN_DROPPED}
        out["provenance"] = {**provenance, "recipe": recipe}
    out["format_version"] = FORMAT_VERSION
    return out


def _config_from(cls: type[FieldConfig] | type[RenderConfig], data: Any, key: str) -> Any:
    """``cls.from_dict(data)``, its refusal naming the metadata key (``render: max_samples ...``)."""
    try:
        return cls.from_dict(data)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint metadata: {key}: {exc}") from None


FACTOR_PREFIXES = ("density_grid.", "appearance_grid.")
"""State-dict prefixes of the VM planes and lines, stored in ``FieldConfig.factor_storage``."""


def is_plane(name: str) -> bool:
    """Whether state-dict entry ``name`` is a VM plane (``<grid>.planes.<i>``, ``[c, h, w]``)."""
    return name.startswith(FACTOR_PREFIXES) and ".planes." in name


def is_coded(name: str, cfg: FieldConfig) -> bool:
    """Whether ``name`` is stored as int8 codes with row scales (``factor_codec``)."""
    return cfg.factor_storage == "int8" and is_plane(name)


def stored_dtype(name: str, dtype: torch.dtype, cfg: FieldConfig) -> torch.dtype:
    """The dtype tensor ``name`` (of ``dtype`` in the field) has in a checkpoint file: int8
    storage codes the planes and keeps the lines (a few hundred values a component) as float16."""
    if name.startswith(FACTOR_PREFIXES):
        if cfg.factor_storage == "int8":
            return torch.int8 if is_plane(name) else torch.float16
        return FACTOR_STORAGE_DTYPES[cfg.factor_storage]
    return torch.uint8 if name == "occupancy" else dtype


def field_tensors(model: VisNerfField) -> dict[str, torch.Tensor]:
    """The tensors stored for a field: factors in the configured storage (int8 planes as codes
    plus ``<name>.row_scale``), occupancy as uint8. A factor that does not fit the storage dtype is
    an error, not a silent infinity."""
    tensors = {}
    for name, value in model.state_dict().items():
        if is_coded(name, model.cfg):
            try:
                codes, scale = encode_rows(value.cpu())  # checks finiteness itself
            except ValueError:
                raise CheckpointError(f"tensor {name!r} has non-finite values, which int8 codes cannot hold") from None
            tensors[name], tensors[name + ROW_SCALE_SUFFIX] = codes.contiguous(), scale.contiguous()
            continue
        stored = value.detach().cpu().to(stored_dtype(name, value.dtype, model.cfg)).contiguous()
        if stored.is_floating_point() and not bool(torch.isfinite(stored).all()):
            raise CheckpointError(f"tensor {name!r} has values that {stored.dtype} cannot hold "
                                  f"(largest magnitude {float(value.abs().max()):.3g})")
        tensors[name] = stored
    return tensors


def decoded_tensors(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The field's state dict from a checkpoint's tensors: int8 planes decoded with their row
    scales (``read_checkpoint`` has checked that every code has its scales)."""
    out = {}
    for name, value in tensors.items():
        if name.endswith(ROW_SCALE_SUFFIX):
            continue
        scale = tensors.get(name + ROW_SCALE_SUFFIX)
        out[name] = value if scale is None else decode_rows(value, scale)
    return out


def save_checkpoint(model: VisNerfField, meta: CheckpointMeta, path: str | Path) -> Path:
    """Write atomically (``write_atomically``)."""
    path = Path(path)
    occ = None if model.occupancy is None else tuple(model.occupancy.shape)
    meta_json = CheckpointMeta(**{**meta.__dict__, "field": model.current_config(), "occupancy_resolution": occ})
    blob = save_safetensors_bytes(field_tensors(model), metadata={METADATA_KEY: meta_json.to_json()})
    return write_atomically(path, blob)


def write_atomically(path: str | Path, blob: bytes) -> Path:
    """Write ``blob`` to ``path`` so that a reader (or a process killed at any instant) sees the
    old file or the whole new one, never a part: a temporary file in the same folder, fsynced,
    then renamed over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_safetensors_header(blob: bytes, max_header_bytes: int = _MAX_HEADER_BYTES) -> dict[str, Any]:
    """The JSON header of a safetensors file's bytes, checked before the tensors are parsed:
    ``CheckpointError`` where the file is too short, the header too long or not a JSON object."""
    if len(blob) < 8:
        raise CheckpointError("file is too short to be a safetensors checkpoint")
    (n,) = struct.unpack("<Q", blob[:8])
    if n > max_header_bytes or n + 8 > len(blob) or blob[8:9] != b"{":
        raise CheckpointError("not a safetensors file (bad header; a pickle or another format?)")
    try:
        header = json.loads(blob[8 : 8 + n])
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise CheckpointError("not a safetensors file (header is not JSON)") from None
    if not isinstance(header, dict):
        raise CheckpointError("not a safetensors file (header is not an object)")
    return header


def expected_shapes(meta: CheckpointMeta) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """Tensor names, shapes and dtypes that a checkpoint with this configuration must hold."""
    with torch.device("meta"):
        model = VisNerfField(meta.field, torch.zeros(2, 3))
    shapes = {}
    for name, value in model.state_dict().items():
        shapes[name] = (tuple(value.shape), stored_dtype(name, value.dtype, meta.field))
        if is_coded(name, meta.field):
            shapes[name + ROW_SCALE_SUFFIX] = ((*value.shape[:-1], 1), torch.float32)
    if meta.occupancy_resolution is not None:
        shapes["occupancy"] = (tuple(meta.occupancy_resolution), torch.uint8)
    return shapes


def read_checkpoint(path: str | Path) -> tuple[CheckpointMeta, dict[str, torch.Tensor]]:
    """Read and validate a checkpoint file; returns metadata and its CPU tensors as stored (int8
    planes as codes beside their ``.row_scale``: ``decoded_tensors`` gives the field's values)."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc.strerror}") from None
    header = read_safetensors_header(blob)
    metadata = header.get("__metadata__") or {}
    if METADATA_KEY not in metadata:
        raise CheckpointError(f"safetensors file has no {METADATA_KEY!r} metadata: not a ViSNeRF checkpoint")
    meta = CheckpointMeta.from_json(metadata[METADATA_KEY])
    try:
        tensors = load_safetensors_bytes(blob)
    except Exception as exc:  # safetensors raises its own error types for truncation / corruption
        raise CheckpointError(f"checkpoint data is corrupt or truncated: {exc}") from None
    expected = expected_shapes(meta)
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing:
        raise CheckpointError(f"checkpoint is missing tensor(s) {missing}")
    if extra:
        raise CheckpointError(f"checkpoint has unexpected tensor(s) {extra}")
    for name, (shape, dtype) in expected.items():
        t = tensors[name]
        if tuple(t.shape) != shape:
            raise CheckpointError(f"tensor {name!r} has shape {list(t.shape)}, configuration says {list(shape)}")
        if t.dtype != dtype:
            raise CheckpointError(f"tensor {name!r} has dtype {t.dtype}, expected {dtype}")
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"tensor {name!r} holds non-finite values (NaN or inf)")
        if name.endswith(ROW_SCALE_SUFFIX) and bool((t < 0).any()):
            raise CheckpointError(f"tensor {name!r} holds negative scales")
    aabb = tensors["aabb"]
    if not bool((aabb[1] > aabb[0]).all()):
        raise CheckpointError("tensor 'aabb' is not a box with positive extent")
    return meta, tensors


def load_checkpoint(path: str | Path, device: torch.device) -> tuple[VisNerfField, CheckpointMeta]:
    """Load a validated checkpoint onto ``device``."""
    meta, tensors = read_checkpoint(path)
    tensors = decoded_tensors(tensors)
    model = VisNerfField(meta.field, tensors["aabb"])
    occupancy = tensors.pop("occupancy", None)
    model.load_state_dict(tensors, strict=True)  # copies into the field's float32 tensors
    model.set_occupancy(None if occupancy is None else occupancy.bool())
    return model.to(device).eval(), meta
