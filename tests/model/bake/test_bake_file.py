"""The bake file: written and read back bit for bit; every broken part refused, named."""

import json
import struct
from dataclasses import replace

import numpy as np
import pytest

from visnerf.bake.bake_file import (
    DENSITY_FILL,
    Bake,
    BakeError,
    BakeHeader,
    bake_bytes,
    parse_bake,
    read_bake,
    write_bake,
)


def small_bake(shading: str = "sh") -> Bake:
    rng = np.random.default_rng(0)
    header = BakeHeader(
        shading=shading, sh_degree=1, cosine_powers=(4, 16) if shading == "level" else (), grid=(10, 7, 5), brick=4,
        aabb=((-1.0, -1.0, -0.5), (1.0, 0.5, 0.5)), density_scale=10.0, step=0.05,
        normal_step=0.02 if shading == "level" else None, early_stop_eps=1e-4, background=(1.0, 1.0, 1.0),
        kind="dvr", title="t", params={"a": 0.25}, source={"checkpoint": "ab"},
    )
    bricks = np.array([[0, 0, 0], [2, 1, 1], [1, 0, 1]], dtype=np.int16)
    c = header.channels
    return Bake(header, bricks, rng.normal(size=(3, 4, 4, 4)).astype(np.float16),
                rng.integers(0, 256, size=(3, 4, 4, 4, c)).astype(np.uint8),
                rng.normal(size=(3, c)).astype(np.float32), rng.random((3, c)).astype(np.float32),
                np.packbits(rng.random(9 * 6 * 4) > 0.5, bitorder="little"))


@pytest.mark.parametrize("shading", ["sh", "level"])
def test_a_bake_reads_back_as_written(tmp_path, shading) -> None:
    bake = small_bake(shading)
    path = tmp_path / "a.bake"
    write_bake(bake, path)
    back = read_bake(path)
    assert back.header == bake.header
    for name, array in bake.arrays().items():
        assert np.array_equal(getattr(back, name), array), name
    assert not (tmp_path / "a.bake.part").exists()


def test_the_layout_is_safetensors() -> None:
    """A length, a JSON header whose __metadata__ holds the bake's header, aligned raw arrays."""
    data = bake_bytes(small_bake())
    (n,) = struct.unpack("<Q", data[:8])
    assert n % 8 == 0
    entries = json.loads(data[8:8 + n])
    assert json.loads(entries["__metadata__"]["bake"])["format"] == "visnerf-bake"
    begin, end = entries["raw"]["data_offsets"]
    raw = np.frombuffer(data[8 + n + begin:8 + n + end], dtype="<f2").reshape(entries["raw"]["shape"])
    assert np.array_equal(raw, small_bake().raw)


def test_dense_arrays_put_each_brick_in_place() -> None:
    bake = small_bake()
    raw = bake.dense_raw()
    assert raw.shape == (5, 7, 10)
    # brick (x=2, y=1, z=1) of 4 covers x 8..9, y 4..6, z 4 (the grid ends there)
    assert np.array_equal(raw[4:5, 4:7, 8:10], bake.raw[1, :1, :3, :2].astype(np.float32))
    assert raw[0, 6, 6] == DENSITY_FILL  # brick (1, 1, 0) is not stored
    coef = bake.dense_coefficients()
    expected = bake.low[0] + bake.codes[0, 1, 2, 3].astype(np.float32) * bake.scale[0]
    assert np.allclose(coef[1, 2, 3], expected)
    occ = bake.dense_occupancy()
    assert occ.shape == (4, 6, 9)
    bits = np.unpackbits(bake.occupancy, bitorder="little")
    assert occ[2, 3, 4] == bool(bits[(2 * 6 + 3) * 9 + 4])


def _corrupt(entries_edit=None, header_edit=None, body=None) -> bytes:
    data = bake_bytes(small_bake())
    (n,) = struct.unpack("<Q", data[:8])
    entries = json.loads(data[8:8 + n])
    rest = data[8 + n:] if body is None else body
    if header_edit:
        doc = json.loads(entries["__metadata__"]["bake"])
        header_edit(doc)
        entries["__metadata__"]["bake"] = json.dumps(doc)
    if entries_edit:
        entries_edit(entries)
    head = json.dumps(entries).encode()
    return struct.pack("<Q", len(head)) + head + rest


@pytest.mark.parametrize(("data", "message"), [
    (b"", "8-byte header length"),
    (struct.pack("<Q", 1 << 40) + b"{}", "header length"),
    (struct.pack("<Q", 4) + b"nope", "not JSON"),
    (_corrupt(header_edit=lambda d: d.update(version=9)), "version 9"),
    (_corrupt(header_edit=lambda d: d.update(format="other")), "not a bake file"),
    (_corrupt(header_edit=lambda d: d.update(shading="phong")), "shading"),
    (_corrupt(header_edit=lambda d: d.update(grid=[1, 7, 5])), "grid"),
    (_corrupt(header_edit=lambda d: d.update(step=-1.0)), "step"),
    (_corrupt(header_edit=lambda d: d.pop("title")), "missing ['title']"),
    (_corrupt(header_edit=lambda d: d.update(density_scale="x")), "density_scale"),
    (_corrupt(entries_edit=lambda e: e["raw"].update(dtype="F64")), "dtype 'F64'"),
    (_corrupt(entries_edit=lambda e: e["raw"].update(dtype="F32")), "bytes"),
    (_corrupt(entries_edit=lambda e: e["codes"].update(shape=[3, 4, 4, 4, 3])), "bytes"),
    (_corrupt(entries_edit=lambda e: e.pop("low")), "arrays"),
    (_corrupt(body=b"\0" * 10), "bytes"),
])
def test_a_broken_file_is_refused_naming_the_problem(data, message) -> None:
    with pytest.raises(BakeError, match=message.replace("[", r"\[").replace("]", r"\]")):
        parse_bake(data)


def test_values_that_break_the_format_are_refused() -> None:
    bake = small_bake()
    raw = bake.raw.copy()
    raw[0, 0, 0, 0] = np.inf
    with pytest.raises(BakeError, match="raw holds a value that is not finite"):
        bake_bytes(replace(bake, raw=raw))
    with pytest.raises(BakeError, match="outside the grid"):
        bake_bytes(replace(bake, bricks=np.array([[0, 0, 0], [3, 0, 0], [1, 0, 1]], dtype=np.int16)))
    with pytest.raises(BakeError, match="stored twice"):
        bake_bytes(replace(bake, bricks=np.array([[0, 0, 0], [0, 0, 0], [1, 0, 1]], dtype=np.int16)))
    with pytest.raises(BakeError, match="codes must have shape"):
        bake_bytes(replace(bake, codes=bake.codes[..., :3]))
    with pytest.raises(BakeError, match="low must be F32"):
        bake_bytes(replace(bake, low=bake.low.astype(np.float64)))


def test_a_file_that_cannot_be_read_is_a_bake_error(tmp_path) -> None:
    with pytest.raises(BakeError, match="cannot read bake"):
        read_bake(tmp_path / "missing.bake")
