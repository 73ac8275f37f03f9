"""The packed landmark state's byte layout (hdmap/mapping/estimator/packing.py): the version table,
encode/decode, and nothing but ValueError out of decode for any bytes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hdmap.mapping.estimator import EstimatorConfig, LandmarkSums
from hdmap.mapping.estimator.packing import (
    OLD_PACK_VERSIONS,
    OPEN_DTYPE,
    OPEN_DTYPE_V1,
    OPEN_DTYPE_V2,
    OPEN_DTYPE_V3,
    OPEN_DTYPE_V4,
    OPEN_DTYPE_V5,
    OPEN_DTYPE_V6,
    PACK_VERSION,
    ROW_DTYPE,
    ROW_DTYPE_V2,
    ROW_DTYPE_V4,
    ROW_DTYPE_V5,
    ROW_FIELDS,
    ROW_FIELDS_V2,
    ROW_FIELDS_V4,
    ROW_FIELDS_V5,
    Layout,
    decode,
    encode,
    layout,
)
from tests.support.estimator import SIGN, passes

UNKNOWN = "unknown landmark state version"


def test_layout_table():
    """Each version's records and their sizes, as the module's docstring gives them."""
    table = {
        7: (ROW_DTYPE, ROW_FIELDS, OPEN_DTYPE, 588, 448),
        6: (ROW_DTYPE_V5, ROW_FIELDS_V5, OPEN_DTYPE_V6, 572, 224),
        5: (ROW_DTYPE_V5, ROW_FIELDS_V5, OPEN_DTYPE_V5, 572, 184),
        4: (ROW_DTYPE_V4, ROW_FIELDS_V4, OPEN_DTYPE_V4, 564, 176),
        3: (ROW_DTYPE_V4, ROW_FIELDS_V4, OPEN_DTYPE_V3, 564, 112),
        2: (ROW_DTYPE_V2, ROW_FIELDS_V2, OPEN_DTYPE_V2, 548, 104),
        1: (ROW_DTYPE_V2, ROW_FIELDS_V2, OPEN_DTYPE_V1, 548, 96),
    }
    assert set(table) == {PACK_VERSION, *OLD_PACK_VERSIONS}
    for v, (row, fields, op, row_bytes, open_bytes) in table.items():
        lay = layout(v)
        assert lay == Layout(v, row, fields, op)
        assert (lay.row.itemsize, lay.open.itemsize) == (row_bytes, open_bytes)
        assert set(lay.fields) | {"n_open"} == set(lay.row.names)
    # packed sizes quoted in sums.py, docs/estimator.md and BENCHMARKS.md
    assert 1 + layout(4).row.itemsize == 565 and 1 + layout(5).row.itemsize == 573


def test_layout_is_frozen():
    with pytest.raises(AttributeError):
        layout(5).version = 4  # type: ignore[misc]


@pytest.mark.parametrize("version", [0, 8, 9, 255, -1])
def test_unknown_version_raises(version):
    with pytest.raises(ValueError, match=UNKNOWN):
        layout(version)
    if 0 <= version <= 255:
        with pytest.raises(ValueError, match=UNKNOWN):
            decode(bytes([version]) + bytes(ROW_DTYPE.itemsize))


def test_empty_blob_raises():
    with pytest.raises(ValueError, match=UNKNOWN):
        decode(b"")


def test_short_blob_raises_value_error():
    with pytest.raises(ValueError):
        decode(bytes([5]) + bytes(ROW_DTYPE_V5.itemsize - 1))
    rec = np.zeros((), ROW_DTYPE_V5)
    rec["n_open"] = 2
    with pytest.raises(ValueError):
        decode(encode(layout(5), rec, np.zeros(1, OPEN_DTYPE_V5)))


@pytest.mark.parametrize("version", [1, 2, 3, 4, 5, 6, 7])
def test_encode_decode_round_trip(version):
    lay = layout(version)
    rng = np.random.default_rng(version)
    rec = np.zeros((), lay.row)
    for f in lay.fields:
        rec[f] = rng.integers(-1000, 1000, np.shape(rec[f]))
    rec["n_open"] = 3
    op = np.zeros(3, lay.open)
    for f in lay.open.names:
        op[f] = rng.integers(-1000, 1000, op[f].shape)
    blob = encode(lay, rec, op)
    assert blob[0] == version
    assert len(blob) == 1 + lay.row.itemsize + 3 * lay.open.itemsize
    back, rec2, op2 = decode(blob + b"trailing bytes are ignored")
    assert back is lay
    assert rec2.tobytes() == rec.tobytes()
    assert op2.tobytes() == op.tobytes()
    assert encode(back, rec2, op2) == blob


def test_pack_rows_writes_the_layouts():
    """Rows without a pull pack as version 4, with one as version 5; both decode to the
    row's state and its open passes."""
    clusters, rays = passes(np.random.default_rng(0), 3, 0)
    for cfg, version in ((EstimatorConfig(), 4), (EstimatorConfig(extra_sigma_pos_m=2.0), 5)):
        s = LandmarkSums(cfg)
        row = s.new_rows(1, [SIGN])
        s.accumulate(np.zeros(len(rays), np.int64), clusters, rays)
        (blob,) = s.pack_rows(row)
        lay, rec, op = decode(blob)
        assert lay is layout(version)
        assert len(blob) == 1 + lay.row.itemsize + 3 * lay.open.itemsize
        assert int(rec["n_obs"]) == len(rays) and int(rec["n_open"]) == op.size == 3
        assert sorted(op["cluster"].tolist()) == s.open_clusters(0) == [0, 1, 2]


@st.composite
def blobs(draw) -> bytes:
    """Anything, or a known version byte, a row record of about the right size with a
    small (also negative) ``n_open``, and a tail of any length."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=1200))
    v = draw(st.integers(0, 7))
    row = ROW_DTYPE_V2 if v < 3 else ROW_DTYPE_V4 if v < 5 else ROW_DTYPE
    size = row.itemsize + draw(st.integers(-2, 2))
    body = bytearray(draw(st.binary(min_size=size, max_size=size)))
    at = row.fields["n_open"][1]
    if size >= at + 4:
        body[at : at + 4] = draw(st.integers(-3, 4)).to_bytes(4, "little", signed=True)
    return bytes([v]) + bytes(body) + draw(st.binary(max_size=800))


@settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(blobs())
def test_decode_returns_or_raises_value_error(blob):
    try:
        lay, rec, op = decode(blob)
    except ValueError:
        return
    assert lay.version == blob[0]
    assert rec.dtype == lay.row and op.dtype == lay.open
    assert len(blob) >= 1 + lay.row.itemsize + op.size * lay.open.itemsize
    assert int(rec["n_open"]) == op.size >= 0


def test_negative_n_open_is_refused():
    rec = np.zeros((), ROW_DTYPE)
    rec["n_open"] = -1
    blob = encode(layout(5), rec, np.zeros(2, OPEN_DTYPE))
    with pytest.raises(ValueError, match="n_open -1"):
        decode(blob)
