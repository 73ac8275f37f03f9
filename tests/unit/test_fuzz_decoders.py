"""Fuzz of every decoder (bounded hypothesis) and named bad batches: each hostile input
decodes or raises one DecodeError naming the field. Inputs from tests/hostile.py."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given

from schemas import (
    AssocGroup,
    DecodeError,
    ErrorReply,
    LandmarkUpdates,
    LogEntry,
    LogHead,
    LogMark,
    LogQuery,
    MapDelta,
    MapSnapshot,
    ObservationBatch,
    ObsGroup,
    Stats,
    UploadAck,
)
from tests.support.hostile import (
    FUZZ,
    Case,
    hostile,
    named_batches,
    valid_messages,
)

# --- decoders ---------------------------------------------------------------------------------

MESSAGES = (ObservationBatch, UploadAck, LogEntry, LogQuery, LogHead, LogMark, ObsGroup, AssocGroup)
MESSAGES += (LandmarkUpdates, MapDelta, MapSnapshot, ErrorReply, Stats)
DECODERS: dict[str, tuple[str, Callable[[bytes], Any]]] = {
    m.__name__: (m.TYPE, m.from_bytes) for m in MESSAGES
}
DECODERS["ObservationBatch.partial"] = ("obs_batch", ObservationBatch.from_bytes_partial)


def check_decoder(name: str, decode: Callable[[bytes], Any], case: Case) -> None:
    try:
        out = decode(case.data)
    except DecodeError as e:
        assert e.field and e.reason, case
        assert not case.must_pass, f"{case} refused: {e}"
        assert case.explains(e.field), f"{case}: error names {e.field!r}: {e}"
        if case.row is not None and e.index is not None and case.must_fail:
            assert e.index == case.row, f"{case}: error on row {e.index}"
        return
    if name == "ObservationBatch.partial":
        _, rejected = out
        if case.row is not None and case.must_fail:
            assert [r.field for r in rejected] == [case.field], f"{case}: rejections {rejected}"
            return
        if case.must_pass:
            assert not rejected, f"{case}: rejections {rejected}"
    assert not case.must_fail, f"{case} was accepted"


@pytest.mark.parametrize("name", sorted(DECODERS))
def test_fuzz_decoder(name: str) -> None:
    mtype, decode = DECODERS[name]
    now = time.time()
    base = valid_messages(now)[mtype]
    decode(base)  # the starting point is valid

    @FUZZ
    @given(hostile(base, now))
    def run(case: Case) -> None:
        check_decoder(name, decode, case)

    run()


@pytest.mark.parametrize("case", named_batches(time.time()), ids=lambda c: c[0])
def test_named_bad_batches_name_their_field(case) -> None:
    _name, payload, field, row = case
    with pytest.raises(DecodeError) as exc:
        ObservationBatch.from_bytes(payload)
    assert (exc.value.field, exc.value.index) == (field, row)
    if row is None:  # a whole-batch error: the partial decoder refuses it the same way
        with pytest.raises(DecodeError) as again:
            ObservationBatch.from_bytes_partial(payload)
        assert again.value.field == field
    else:  # a bad row: only that row is rejected
        batch, rejected = ObservationBatch.from_bytes_partial(payload)
        assert [r.field for r in rejected] == [field] and len(batch.obs) == 3
