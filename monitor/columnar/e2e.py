"""AUTOSAR E2E profile 2 checked on whole columns of payloads.

The reference is what the per-frame codecs call, `cantools.autosar.end_to_end`
(`check_profile2_crc`), which computes CRC-8/AUTOSAR with ``crccheck.crc.Crc8Autosar`` over
bytes ``1 .. payload_length - 1`` and the data ID that the message's 16-entry DataIDList
assigns to the frame's alive counter (low nibble of byte 1); the CRC is byte 0.

Nothing here writes the polynomial down: the byte table is generated from the library
itself. For a CRC whose register is 8 bits wide and is neither reflected on input nor on
output, one byte b moves the register r to ``T[r ^ b]``, and a one-byte message gives
``calc([b]) = T[init ^ b] ^ xorout``; so ``T[v] = calc([v ^ init]) ^ xorout``, with init and
xorout read from the library's class. `crc_table` then checks the table against cantools'
own `compute_profile2_crc` on a fixed set of payloads and refuses to run if they differ
(the tests check it on random ones too).
"""

from __future__ import annotations

import functools

import crccheck
import numpy as np
from cantools.autosar.end_to_end import compute_profile2_crc
from cantools.database.can import Message
from numpy.typing import NDArray

__all__ = ["crc_table", "profile2_ok", "profile2_params"]


@functools.cache
def crc_table() -> NDArray[np.uint8]:
    """The CRC-8/AUTOSAR byte table, generated from crccheck and verified against cantools."""
    cls = crccheck.crc.Crc8Autosar
    if cls._width != 8 or cls._reflect_input or cls._reflect_output:
        raise RuntimeError("crccheck's Crc8Autosar is not a plain 8-bit CRC any more")
    init, xorout = int(cls._initvalue), int(cls._xor_output)
    table = np.array([cls().calc(bytes([v ^ init])) ^ xorout for v in range(256)], np.uint8)
    rng = np.random.default_rng(20240611)
    payloads = rng.integers(0, 256, (64, 8), dtype=np.uint8)
    data_ids = rng.integers(0, 256, 64)
    got = _crc(table, payloads, 8, data_ids.astype(np.uint8), int(init), int(xorout))
    want = [compute_profile2_crc(bytes(p), int(d)) for p, d in zip(payloads, data_ids,
                                                                   strict=True)]
    if got.tolist() != want:
        raise RuntimeError("the generated CRC table disagrees with cantools' profile 2 CRC")
    return table


def _crc(table: NDArray[np.uint8], data: NDArray[np.uint8], protected: int,
         data_id: NDArray[np.uint8], init: int, xorout: int) -> NDArray[np.uint8]:
    reg = np.full(data.shape[0], init, np.uint8)
    for j in range(1, protected):
        reg = table[reg ^ data[:, j]]
    reg = table[reg ^ data_id]
    return reg ^ np.uint8(xorout)


def profile2_params(message: Message) -> tuple[NDArray[np.uint8], int] | None:
    """(DataIDList, protected length) as cantools reads them off `message`, None if the
    message carries no profile-2 properties (then cantools' check gives None: rejected)."""
    a = message.autosar
    if a is None or a.e2e is None or a.e2e.data_ids is None or len(a.e2e.data_ids) != 16:
        return None
    return np.array(a.e2e.data_ids, dtype=np.uint8), int(a.e2e.payload_length)


def profile2_ok(message: Message, data: NDArray[np.uint8], length: int) -> NDArray[np.bool_]:
    """For payloads of `length` bytes (rows of `data`, (n, 8)), whether
    `check_profile2_crc(payload, message)` is true."""
    n = data.shape[0]
    params = profile2_params(message)
    if params is None or length < 2:
        return np.zeros(n, np.bool_)
    ids, protected = params
    protected = min(protected, length)  # cantools slices payload[1:protected]
    cls = crccheck.crc.Crc8Autosar
    did = ids[data[:, 1] & 0x0F]
    crc = _crc(crc_table(), data, protected, did, int(cls._initvalue), int(cls._xor_output))
    ok: NDArray[np.bool_] = crc == data[:, 0]
    return ok
