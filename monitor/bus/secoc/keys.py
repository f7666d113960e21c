"""SecOC keys: an AES-128/256 key from a file only its owner can access.

`load_key` reads the file the service is given (``--key FILE``, systemd
``LoadCredential=``), refusing one its group or others can access; `parse_key` reads 32 or
64 hex digits or 16/32 raw bytes; `check_key` is the length check every key passes
before it keys an AES-CMAC. `read_guarded` is the careful read both the key file and the
freshness state file (`monitor.bus.secoc.state`) go through.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Final

from monitor.bus.errors import SecOCError
from monitor.files import UserFileError, read_user_file

__all__ = ["KEY_LENGTHS", "check_key", "load_key", "parse_key", "read_guarded"]

KEY_LENGTHS: Final[tuple[int, ...]] = (16, 32)
"""AES-128 and AES-256 key lengths in bytes."""
_MAX_KEY_FILE: Final = 4096
_HEX_DIGITS: Final = frozenset(b"0123456789abcdefABCDEF")
_TEXT: Final = frozenset(range(0x20, 0x7F)) | frozenset(b"\t\n\r")


def check_key(key: bytes) -> bytes:
    """`key` as bytes if it is 16 or 32 bytes long (AES-128/256), else `SecOCError`."""
    if not isinstance(key, bytes | bytearray) or len(key) not in KEY_LENGTHS:
        got = f"{len(key)} bytes" if isinstance(key, bytes | bytearray) else type(key).__name__
        raise SecOCError(f"SecOC key must be 16 or 32 bytes (AES-128/256), got {got}")
    return bytes(key)


def parse_key(data: bytes, where: str = "key") -> bytes:
    """An AES key from 32 or 64 hex digits (surrounding whitespace ignored) or 16/32 raw bytes.

    Content that is all printable text is read as hex only (so a mistyped hex key is an
    error, not 32 raw bytes); random raw keys are text with probability about 1e-14.
    """
    text = data.strip()
    if len(text) in (32, 64) and all(b in _HEX_DIGITS for b in text):
        return bytes.fromhex(text.decode("ascii"))
    if len(data) in KEY_LENGTHS and not all(b in _TEXT for b in data):
        return bytes(data)
    raise SecOCError(
        f"{where}: not an AES key: expected 32 or 64 hex digits (AES-128/256) or 16 or 32 "
        f"raw bytes, got {len(data)} bytes"
    )


def load_key(path: str | os.PathLike[str], *, allow_insecure: bool = False) -> bytes:
    """Read an AES-128/256 key for SecOC from `path` (format: `parse_key`).

    The file must be a regular file that neither its group nor others can access
    (``mode & 0o077 == 0``, e.g. ``chmod 600``) unless `allow_insecure`. Every problem is
    one `SecOCError` line; the key itself never appears in a message.
    """
    p = Path(path)
    data = read_guarded(p, "key file", refused_mode=0 if allow_insecure else 0o077,
                        refused_as="accessible",
                        advice="make it readable only by the service (chmod 600)",
                        limit=_MAX_KEY_FILE)
    if data is None:
        raise SecOCError(f"{p}: key file not found")
    return parse_key(data, str(p))


def read_guarded(path: Path, what: str, *, refused_mode: int, refused_as: str, advice: str,
                 limit: int) -> bytes | None:
    """The content of the regular file `path`, at most `limit` bytes; None if it does not
    exist.

    Read with `monitor.files.read_user_file`, so a FIFO or device never blocks and a large
    file is refused before it is read. `SecOCError` (one line, naming `what` and `path`) if
    it cannot be read, is not a regular file, is larger than `limit` or has any permission
    bit of `refused_mode` (a file its group or others are `refused_as`, "accessible" or
    "writable": the message ends with `advice`). The mode is checked on the file opened,
    not on whatever the path names by then, and before any byte is read.
    """

    def check(st: os.stat_result) -> None:
        mode = stat.S_IMODE(st.st_mode)
        if mode & refused_mode:
            raise SecOCError(f"{path}: {what} is {refused_as} by group or others (mode "
                             f"{mode:04o}); {advice}")

    try:
        return read_user_file(path, what=what, limit=limit, check=check)
    except UserFileError as exc:
        if exc.errno == errno.ENOENT:
            return None
        raise SecOCError(str(exc)) from None
