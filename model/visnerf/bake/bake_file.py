"""The bake file: one parameter setting of a model as bricks of a vertex grid (docs/bake_format.md).

The layout is safetensors': an unsigned 64-bit little-endian header length, a JSON header and raw
little-endian arrays, so that a browser reads it with ``DataView`` and ``JSON.parse`` and no
library. The header's ``__metadata__`` holds one entry, ``bake``: the JSON of ``BakeHeader``.
Reading checks everything a renderer relies on (lengths, dtypes, shapes, offsets, ranges and
finite values) and raises ``BakeError`` naming the first problem.
"""

import json
import math
import struct
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

FORMAT = "visnerf-bake"
VERSION = 1
Shading = Literal["sh", "level"]
MAX_HEADER_BYTES = 1 << 20
DENSITY_FILL = -100.0
"""Raw density of a vertex no occupied cell uses: its activation is 0 in float32 (the raw density
is the softplus's whole argument, the model's shift and level included)."""
_DTYPES: dict[str, np.dtype] = {"F16": np.dtype("<f2"), "F32": np.dtype("<f4"), "U8": np.dtype("u1"),
                                 "I16": np.dtype("<i2")}
_NAMES = {v: k for k, v in _DTYPES.items()}


class BakeError(ValueError):
    """A bake file (or a bake about to be written) that breaks the format; the message names why."""


def basis_size(shading: Shading, sh_degree: int, cosine_powers: tuple[int, ...]) -> int:
    """Basis functions of a vertex's colour fit: spherical harmonics of degree ``sh_degree``;
    ``level`` adds the cosine of the level field's normal with the view and its powers."""
    n = (sh_degree + 1) ** 2
    return n + 1 + len(cosine_powers) if shading == "level" else n


@dataclass(frozen=True)
class BakeHeader:
    """What a renderer needs besides the arrays; world units, axes x, y, z."""

    shading: Shading
    """``sh``: colour logits are a sum of spherical harmonics of the view direction; ``level``: of
    degree-1 harmonics, the cosine of the level field's normal with the view and that cosine's
    positive part to each of ``cosine_powers`` (the normal from four probes of the raw density
    ``normal_step`` away, as the model's colour decoder reads it)."""
    sh_degree: int
    cosine_powers: tuple[int, ...]
    grid: tuple[int, int, int]
    """Vertices along x, y, z; vertex ``i`` of an axis lies at ``aabb[0] + i * (aabb[1] - aabb[0]) / (n - 1)``."""
    brick: int
    aabb: tuple[tuple[float, float, float], tuple[float, float, float]]
    density_scale: float
    """Density (per world unit) = ``softplus(raw) * density_scale``, raw interpolated trilinearly."""
    step: float
    """Sample spacing along a ray, world units."""
    normal_step: float | None
    early_stop_eps: float
    background: tuple[float, float, float]
    kind: str
    title: str
    params: dict[str, float]
    """The setting baked: every parameter's value by name."""
    source: dict[str, str] = field(default_factory=dict)
    """Where it came from: the checkpoint's content hash, the bake's own parameters."""
    format: str = FORMAT
    version: int = VERSION

    @property
    def n_basis(self) -> int:
        return basis_size(self.shading, self.sh_degree, self.cosine_powers)

    @property
    def channels(self) -> int:
        """Coefficients a vertex: ``n_basis`` times r, g, b (basis-major: channel ``3 k + c``)."""
        return 3 * self.n_basis

    @property
    def brick_grid(self) -> tuple[int, int, int]:
        """Bricks along x, y, z."""
        return tuple(-(-n // self.brick) for n in self.grid)  # type: ignore[return-value]

    @property
    def cells(self) -> tuple[int, int, int]:
        return tuple(n - 1 for n in self.grid)  # type: ignore[return-value]

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str) -> "BakeHeader":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise BakeError(f"the bake header is not JSON: {exc}") from None
        if not isinstance(doc, dict):
            raise BakeError("the bake header must be a JSON object")
        if doc.get("format") != FORMAT:
            raise BakeError(f"not a bake file: format {doc.get('format')!r}, expected {FORMAT!r}")
        if doc.get("version") != VERSION:
            raise BakeError(f"bake format version {doc.get('version')!r} is not supported (this reads {VERSION})")
        names = set(cls.__dataclass_fields__)
        missing, extra = sorted(names - set(doc)), sorted(set(doc) - names)
        if missing or extra:
            raise BakeError(f"bake header fields: missing {missing}, unknown {extra}")
        try:
            header = cls(
                shading=doc["shading"], sh_degree=_whole(doc["sh_degree"], "sh_degree"),
                cosine_powers=tuple(_whole(p, "cosine_powers") for p in doc["cosine_powers"]),
                grid=tuple(_whole(n, "grid") for n in doc["grid"]),  # type: ignore[arg-type]
                brick=_whole(doc["brick"], "brick"),
                aabb=tuple(tuple(_number(v, "aabb") for v in corner) for corner in doc["aabb"]),  # type: ignore[arg-type]
                density_scale=_number(doc["density_scale"], "density_scale"),
                step=_number(doc["step"], "step"),
                normal_step=None if doc["normal_step"] is None else _number(doc["normal_step"], "normal_step"),
                early_stop_eps=_number(doc["early_stop_eps"], "early_stop_eps"),
                background=tuple(_number(v, "background") for v in doc["background"]),  # type: ignore[arg-type]
                kind=str(doc["kind"]), title=str(doc["title"]),
                params={str(k): _number(v, f"params.{k}") for k, v in dict(doc["params"]).items()},
                source={str(k): str(v) for k, v in dict(doc["source"]).items()},
            )
        except (TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, BakeError):
                raise
            raise BakeError(f"bake header: {exc}") from None
        header.check()
        return header

    def check(self) -> None:
        """BakeError naming the first field out of its range."""
        if self.shading not in ("sh", "level"):
            raise BakeError(f"shading must be 'sh' or 'level', got {self.shading!r}")
        if not 0 <= self.sh_degree <= 3:
            raise BakeError(f"sh_degree must be within [0, 3], got {self.sh_degree}")
        if self.shading == "level" and self.normal_step is None:
            raise BakeError("a level bake needs normal_step")
        if len(self.grid) != 3 or min(self.grid) < 2 or math.prod(self.grid) > 1 << 28:
            raise BakeError(f"grid must be three axes of 2 or more vertices (2^28 at most), got {self.grid}")
        if not 2 <= self.brick <= 64:
            raise BakeError(f"brick must be within [2, 64], got {self.brick}")
        lo, hi = self.aabb
        if len(lo) != 3 or len(hi) != 3 or not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise BakeError(f"aabb must be a box with its lower corner below its upper one, got {self.aabb}")
        if not (self.density_scale > 0 and self.step > 0 and 0 <= self.early_stop_eps < 1):
            raise BakeError("density_scale and step must be positive, early_stop_eps within [0, 1)")
        if self.normal_step is not None and not self.normal_step > 0:
            raise BakeError(f"normal_step must be positive, got {self.normal_step}")
        if len(self.background) != 3 or not all(0.0 <= v <= 1.0 for v in self.background):
            raise BakeError(f"background must be three values within [0, 1], got {self.background}")


def _whole(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise BakeError(f"{name} must hold whole numbers, got {value!r}")
    return value


def _number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BakeError(f"{name} must hold finite numbers, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Bake:
    """One baked setting. Arrays (``n`` stored bricks, ``B`` = ``header.brick``, ``C`` = ``header.channels``):

    - ``bricks`` int16 [n, 3]: brick coordinates along x, y, z, each brick once;
    - ``raw`` float16 [n, B, B, B] (z, y, x): the argument of the density's softplus, ``DENSITY_FILL``
      where no occupied cell reads it;
    - ``codes`` uint8 [n, B, B, B, C]: colour coefficients, ``low + code * scale``;
    - ``low``, ``scale`` float32 [n, C]: each brick's channels' offsets and steps;
    - ``occupancy`` uint8 [ceil(cells / 8)]: one bit a cell (x fastest, then y, then z; bit ``i``
      of a byte is cell ``8 byte + i``), set where the renderer samples.
    """

    header: BakeHeader
    bricks: np.ndarray
    raw: np.ndarray
    codes: np.ndarray
    low: np.ndarray
    scale: np.ndarray
    occupancy: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        return {"bricks": self.bricks, "raw": self.raw, "codes": self.codes, "low": self.low,
                "scale": self.scale, "occupancy": self.occupancy}

    def check(self) -> None:
        """BakeError naming the first array whose dtype, shape, range or values break the format."""
        h = self.header
        h.check()
        n, b, c = self.bricks.shape[0] if self.bricks.ndim == 2 else -1, h.brick, h.channels
        expected = {"bricks": ("I16", (n, 3)), "raw": ("F16", (n, b, b, b)), "codes": ("U8", (n, b, b, b, c)),
                    "low": ("F32", (n, c)), "scale": ("F32", (n, c)),
                    "occupancy": ("U8", (-(-math.prod(h.cells) // 8),))}
        for name, (dtype, shape) in expected.items():
            array = getattr(self, name)
            if _NAMES.get(array.dtype.newbyteorder("<")) != dtype:
                raise BakeError(f"{name} must be {dtype}, got {array.dtype}")
            if tuple(array.shape) != shape:
                raise BakeError(f"{name} must have shape {list(shape)}, got {list(array.shape)}")
        if n:
            if (self.bricks < 0).any() or (self.bricks >= np.array(h.brick_grid)).any():
                raise BakeError(f"a brick lies outside the grid's {list(h.brick_grid)} bricks")
            if len(np.unique(self.bricks, axis=0)) != n:
                raise BakeError("a brick is stored twice")
        for name in ("raw", "low", "scale"):
            if not np.isfinite(getattr(self, name)).all():
                raise BakeError(f"{name} holds a value that is not finite")
        if (self.scale < 0).any():
            raise BakeError("scale must not be negative")

    def dense_raw(self) -> np.ndarray:
        """float32 [nz, ny, nx] raw density over the whole grid (``DENSITY_FILL`` outside the bricks)."""
        return self._dense(self.raw.astype(np.float32)[..., None], DENSITY_FILL)[..., 0]

    def dense_coefficients(self) -> np.ndarray:
        """float32 [nz, ny, nx, C] colour coefficients over the whole grid (0 outside the bricks)."""
        values = self.low[:, None, None, None, :] + self.codes.astype(np.float32) * self.scale[:, None, None, None, :]
        return self._dense(values, 0.0)

    def dense_occupancy(self) -> np.ndarray:
        """bool [nz - 1, ny - 1, nx - 1]: the cells the renderer samples."""
        cx, cy, cz = self.header.cells
        bits = np.unpackbits(self.occupancy, bitorder="little")[: cx * cy * cz]
        return bits.reshape(cz, cy, cx).astype(bool)

    def _dense(self, values: np.ndarray, fill: float) -> np.ndarray:
        h, b = self.header, self.header.brick
        bx, by, bz = h.brick_grid
        out = np.full((bz * b, by * b, bx * b, values.shape[-1]), fill, dtype=np.float32)
        for (x, y, z), block in zip(self.bricks.astype(np.int64), values, strict=True):
            out[z * b:(z + 1) * b, y * b:(y + 1) * b, x * b:(x + 1) * b] = block
        nx, ny, nz = h.grid
        return out[:nz, :ny, :nx]

    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays().values())


def bake_bytes(bake: Bake) -> bytes:
    """The file's bytes (the bake checked first)."""
    bake.check()
    entries: dict[str, object] = {"__metadata__": {"bake": bake.header.to_json()}}
    offset, chunks = 0, []
    for name, array in bake.arrays().items():
        data = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<")).tobytes()
        entries[name] = {"dtype": _NAMES[array.dtype.newbyteorder("<")], "shape": list(array.shape),
                         "data_offsets": [offset, offset + len(data)]}
        chunks.append(data)
        offset += len(data)
    header = json.dumps(entries, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 8)  # the arrays start 8-byte aligned
    return struct.pack("<Q", len(header)) + header + b"".join(chunks)


def write_bake(bake: Bake, path: str | Path) -> int:
    """Write atomically (a partial file never replaces a good one); the bytes written."""
    target = Path(path)
    data = bake_bytes(bake)
    tmp = target.with_name(target.name + ".part")
    tmp.write_bytes(data)
    tmp.replace(target)
    return len(data)


def parse_bake(data: bytes) -> Bake:
    """The bake in ``data``, checked; BakeError names the first problem."""
    if len(data) < 8:
        raise BakeError(f"a bake file starts with an 8-byte header length; this one has {len(data)} bytes")
    (n,) = struct.unpack("<Q", data[:8])
    if n < 2 or n > MAX_HEADER_BYTES or 8 + n > len(data):
        raise BakeError(f"header length {n} does not fit a file of {len(data)} bytes (at most {MAX_HEADER_BYTES})")
    try:
        entries = json.loads(data[8:8 + n].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BakeError(f"the header is not JSON: {exc}") from None
    if not isinstance(entries, dict) or not isinstance(entries.get("__metadata__"), dict):
        raise BakeError("the header must be an object with __metadata__")
    bake_json = entries.pop("__metadata__").get("bake")
    if not isinstance(bake_json, str):
        raise BakeError("__metadata__ has no bake entry")
    header = BakeHeader.from_json(bake_json)
    body = memoryview(data)[8 + n:]
    wanted = ("bricks", "raw", "codes", "low", "scale", "occupancy")
    if sorted(entries) != sorted(wanted):
        raise BakeError(f"the file's arrays are {sorted(entries)}, expected {sorted(wanted)}")
    arrays = {}
    for name in wanted:
        arrays[name] = _array(name, entries[name], body)
    bake = Bake(header, **arrays)
    bake.check()
    return bake


def _array(name: str, entry: object, body: memoryview) -> np.ndarray:
    if not isinstance(entry, dict) or set(entry) != {"dtype", "shape", "data_offsets"}:
        raise BakeError(f"array {name}: an entry needs dtype, shape and data_offsets")
    dtype = _DTYPES.get(str(entry["dtype"]))
    if dtype is None:
        raise BakeError(f"array {name}: dtype {entry['dtype']!r} is not one of {sorted(_DTYPES)}")
    shape, offsets = entry["shape"], entry["data_offsets"]
    if not (isinstance(shape, list) and all(isinstance(s, int) and s >= 0 for s in shape)):
        raise BakeError(f"array {name}: shape must be a list of whole numbers, got {shape!r}")
    if not (isinstance(offsets, list) and len(offsets) == 2 and all(isinstance(o, int) for o in offsets)):
        raise BakeError(f"array {name}: data_offsets must be two whole numbers, got {offsets!r}")
    begin, end = offsets
    if not 0 <= begin <= end <= len(body) or end - begin != math.prod(shape) * dtype.itemsize:
        raise BakeError(f"array {name}: bytes {begin}..{end} do not hold {shape} of {entry['dtype']} "
                        f"within the {len(body)} bytes after the header")
    return np.frombuffer(body[begin:end], dtype=dtype).reshape(shape)


def read_bake(path: str | Path) -> Bake:
    """``parse_bake`` of a file; BakeError also for a file that cannot be read."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise BakeError(f"cannot read bake {path}: {exc.strerror}") from None
    return parse_bake(data)
