"""One frame, one verdict: the per-frame codec (``decode_can``, `check_payload` inside it)
and the column decoder (`monitor.columnar.decode.RouteTable`) built from the same routes
give every frame the same reason -- the first failed check in
`monitor.bus.codec.CHECK_ORDER` -- and, for an accepted frame, the same inputs, outputs,
truth and alive counter. Random frames of every route of our bus (dbc/motor.dbc) and of
the rigs (rigs/, tests/rigs): random or valid payloads, with or without their E2E CRC,
reserved bits set, wrong lengths, the CAN FD flag flipped, the other ID length, remote and
error flags, unknown IDs; several faults in one frame, so that a change of either path's
order of checks is a disagreement Hypothesis finds and shrinks."""

from __future__ import annotations

import contextlib
import math
from typing import Any

import can
import pytest
from cantools.autosar.end_to_end import apply_profile2_crc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from monitor.bus.codec import CHECK_ORDER, Decoded, Rejected, RejectReason, load_database
from monitor.bus.route import Route, RouteSource
from monitor.columnar.chunk import chunk_from_messages
from monitor.columnar.decode import REASONS, NotColumnar, RouteTable
from monitor.rig import build_decoder, load_rig
from tests.support.paths import ROOT, TEST_RIGS

FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def _codecs() -> dict[str, tuple[RouteSource, RouteTable]]:
    """Our bus and every rig, each without a SecOC key (with one, frames go frame by frame:
    `test_secoc_with_a_key_is_not_columnar`)."""
    out: dict[str, tuple[RouteSource, RouteTable]] = {}
    db = load_database()
    out["motor.dbc"] = (db, RouteTable.of(db, 1, 1))
    for path in (*sorted((ROOT / "rigs").glob("*.toml")), *sorted(TEST_RIGS.glob("*.toml"))):
        try:
            rig = load_rig(path)
        except Exception:  # a scenario file beside the rigs, not a rig
            continue
        codec = build_decoder(rig)
        assert isinstance(codec, RouteSource)
        out[path.name] = (codec, RouteTable.of(codec, 8, 8))
    return out


CODECS = _codecs()


def test_the_rigs_are_here() -> None:
    assert {"motor.dbc", "motor.toml", "press.toml", "twin.toml", "servo.toml",
            "fd_servo.toml", "secure_drive.toml"} <= set(CODECS)


def test_secoc_with_a_key_is_not_columnar() -> None:
    """A frame's verdict then depends on its stream's freshness: frame by frame, in order.
    Without a key, secured frames decode unverified and sync frames are plain samples, in
    columns as frame by frame."""
    rig = load_rig(TEST_RIGS / "secure_drive.toml")
    assert not build_decoder(rig).frame_by_frame
    codec = build_decoder(rig, secoc_key=bytes(16))
    assert codec.frame_by_frame
    with pytest.raises(NotColumnar, match="SecOC"):
        RouteTable.of(codec, 8, 8)
    keyed = load_database(secoc_key=bytes(16))
    assert keyed.frame_by_frame and not load_database().frame_by_frame
    with pytest.raises(NotColumnar, match="SecOC"):
        RouteTable.of(keyed, 1, 1)


def _valid_values(route: Route, draw: Any) -> dict[str, float]:
    """Physical values inside every signal's [min, max] (0 where the DBC gives none)."""
    out: dict[str, float] = {}
    for s in route.message.signals:
        lo, hi = s.minimum, s.maximum
        if lo is None or hi is None or not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            out[s.name] = 0.0
        else:
            out[s.name] = draw(st.floats(float(lo), float(hi)))
    return out


@st.composite
def _frame(draw: Any, routes: tuple[Route, ...]) -> can.Message:
    """A frame of a random route, valid or not in random ways."""
    r = draw(st.sampled_from(routes))
    length = r.length
    payload = draw(st.binary(min_size=length, max_size=length))
    if draw(st.booleans()):  # values in range, as a sender writes them
        with contextlib.suppress(Exception):  # one cantools cannot pack: the random one
            payload = bytes(r.message.encode(_valid_values(r, draw), scaling=True,
                                             padding=False, strict=False))
    if r.reserved_mask and draw(st.booleans()):
        n = int.from_bytes(payload, "little") & ~r.reserved_mask
        payload = n.to_bytes(length, "little")
    if r.e2e and draw(st.integers(0, 3)):  # mostly a valid CRC
        protected = apply_profile2_crc(payload, r.message)
        assert protected is not None
        payload = bytes(protected)
    if r.reserved_mask and draw(st.integers(0, 5)) == 0:
        bit = draw(st.sampled_from([i for i in range(8 * length) if r.reserved_mask >> i & 1]))
        payload = (int.from_bytes(payload, "little") | 1 << bit).to_bytes(length, "little")
    is_fd = r.fd
    if draw(st.integers(0, 7)) == 0:
        is_fd = not is_fd
    if draw(st.integers(0, 7)) == 0:  # another length
        new = draw(st.sampled_from(FD_LENGTHS if is_fd else FD_LENGTHS[:9]))
        payload = (payload + bytes(64))[:new]
    if not is_fd and len(payload) > 8:  # no classic frame is longer
        is_fd = True
    fid, ext = r.frame_id, r.extended
    if draw(st.integers(0, 9)) == 0:
        ext = not ext
    if draw(st.integers(0, 9)) == 0:
        fid = draw(st.integers(0, 0x1FFFFFFF if ext else 0x7FF))
    if ext is False and fid > 0x7FF:
        ext = True
    remote = draw(st.integers(0, 15)) == 0
    error = draw(st.integers(0, 15)) == 0
    return can.Message(timestamp=1.0, arbitration_id=fid, is_extended_id=ext,
                       is_remote_frame=remote and not is_fd, is_error_frame=error,
                       is_fd=is_fd, data=b"" if remote and not is_fd else payload,
                       dlc=len(payload), check=False)


def _per_frame(d: Decoded | Rejected, m: int, p: int) -> tuple[Any, ...]:
    """The verdict, and for a sample its columns' values, from the per-frame codec."""
    if isinstance(d, Rejected):
        return (str(d.reason),)
    u = [math.nan] * m
    for i, v in d.inputs:
        u[i] = v
    y = list(d.outputs) + [math.nan] * (p - len(d.outputs))
    return ("", u, y, math.nan if d.truth is None else d.truth,
            -1 if d.counter is None else d.counter)


def _column(res: Any, i: int) -> tuple[Any, ...]:
    reason = REASONS[int(res.code[i])]
    if reason:
        return (reason,)
    return ("", res.u[i].tolist(), res.y[i].tolist(), float(res.truth[i]),
            int(res.counter[i]))


def _plain(v: tuple[Any, ...]) -> list[Any]:
    """`v` flattened, NaN as a word (NaN equals nothing, not even itself)."""
    out: list[Any] = []
    for x in v:
        if isinstance(x, list | tuple):
            out += _plain(tuple(x))
        else:
            out.append("nan" if isinstance(x, float) and math.isnan(x) else x)
    return out


@pytest.mark.parametrize("which", sorted(CODECS))
@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_per_frame_and_column_verdicts_agree(data: Any, which: str) -> None:
    codec, table = CODECS[which]
    frames = data.draw(st.lists(_frame(tuple(codec.routes)), min_size=1, max_size=25))
    res = table.decode(chunk_from_messages(frames))
    for i, msg in enumerate(frames):
        one = _per_frame(codec.decode_can(msg), table.m, table.p)  # type: ignore[attr-defined]
        col = _column(res, i)
        assert _plain(one) == _plain(col), (which, msg, one, col)


def test_the_order_is_every_reason_once() -> None:
    assert sorted(CHECK_ORDER) == sorted(RejectReason)
    assert len(set(CHECK_ORDER)) == len(CHECK_ORDER)
