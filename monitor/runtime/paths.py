"""Where a command's outputs go, checked before it does any work, so that a user's file is
never destroyed: `check_outputs` (files) and `check_directory` (directories), used by every
command that writes (identify, calibrate, replay, run, sim-ecu).

* No output is one of the command's inputs, nor another of its outputs. Files are compared
  by identity, (st_dev, st_ino) as `os.path.samefile` does: a symbolic link, a hard link or
  another spelling of an input's path is that input. The refusal names both options.
* A file output is a regular file (or not there yet) in an existing, writable directory.
* An existing file is replaced (or appended to) only if motor-monitor wrote it
  (`is_own_file`, by the kind of file the output is), or with --force.

The files a command writes whole go through `write_text` and `atomic_output`: a temporary
file beside the target, fsync, rename (`monitor.files`), and a failure is one line naming
the user's file, never the temporary one. Streams (events appended during a run, the
recording written during a replay) cannot be written that way: for them, the rule above on
files motor-monitor did not write is what protects the user's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import stat
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from monitor.errors import MonitorError, UsageError
from monitor.files import KIB, MIB, atomic_replace, file_kind, shown_path

if TYPE_CHECKING:
    from collections.abc import Callable

    from monitor.rig import Rig

__all__ = ["PNG_MAGIC", "RIG_HEADER", "RRD_MAGICS", "Input", "Kind", "Output",
           "atomic_output", "check_directory", "check_outputs", "is_own_file",
           "monitor_inputs", "write_text"]

Kind = Literal["rig", "identify-report", "png", "thresholds", "events", "rrd", "metrics",
               "summary-csv", "summary-parquet", "samples-csv", "samples-parquet"]
"""What an output is, and so how a file of that name is recognised as one motor-monitor
wrote (`is_own_file`)."""

Input = tuple[str, str | os.PathLike[str]]
"""A file the command reads: (the option or argument that names it, its path)."""

RIG_HEADER = "# identified by motor-monitor identify"
"""How a rig file that `identify` wrote begins (the line goes on: the captures, the node)."""

RRD_MAGICS = (b"RRF0", b"RRF1", b"RRF2")
"""The first bytes of a Rerun recording (.rrd): the file header's FourCC of today's SDK
(RRF2, Rerun 0.41) and of the earlier ones."""

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_MATPLOTLIB = b"Matplotlib"  # the Software text chunk matplotlib writes after the header

_HEAD = 4 * KIB  # what is read of a file's start to recognise it
_TAIL = 64 * KIB  # and of its end (an event line is a few hundred bytes)
_REPORT_LIMIT = 16 * MIB  # an identify report is a few kB; larger is not ours
_PARQUET_FOOTER_LIMIT = 4 * MIB

_ROTATED_NAME = re.compile(r".+-\d{8}T\d{6}-\d{4,}\.[A-Za-z0-9]+")
"""The names of the rotated files in --record-dir and --raw-dir (`monitor.files.FileSeries`:
``<prefix>-YYYYmmddTHHMMSS-NNNN<suffix>``), whose oldest are deleted."""


@dataclass(frozen=True)
class Output:
    """A file a command writes: the option that names it (shown in every refusal), its path,
    what kind of file it is (None: no existing file is replaced without its own reader
    having accepted it first, e.g. the SecOC state), whether it is appended to rather than
    replaced, and whether the command creates its missing directories."""

    option: str
    path: Path
    kind: Kind | None
    append: bool = False
    makes_directories: bool = False


def monitor_inputs(rig: Rig, args: Any) -> list[Input]:
    """The files a command reads besides its captures: the rig file, its DBC files (or
    --dbc's), --thresholds and --key (those `args` has and gives)."""
    found: list[Input] = []
    if rig.source is not None:
        found.append(("--rig", rig.source))
    if getattr(args, "dbc", None):
        dbc_option = "--dbc"
    else:
        dbc_option = "the DBC file of --rig" if rig.source is not None else "the built-in DBC"
    found += [(dbc_option, p) for p in rig.dbc]
    for option in ("thresholds", "key"):
        value = getattr(args, option, None)
        if value:
            found.append((f"--{option}", value))
    return found


def _identity(path: str | os.PathLike[str]) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):  # missing or unusable: the reader of the input says so
        return None
    return st.st_dev, st.st_ino


def _named(option: str, path: str | os.PathLike[str]) -> str:
    return f"{option} {shown_path(path)}"


def _nearest_existing(path: Path) -> Path:
    """`path`, or its nearest ancestor that exists."""
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _writable_directory(named: str, directory: str | os.PathLike[str], *,
                        create: bool) -> os.stat_result:
    """The status of `directory` (or, with `create`, of its nearest existing ancestor), after
    refusing in one `UsageError` line, after `named` (an option, with the file that goes in
    the directory if any), one that does not exist, is not a directory or is not
    writable."""
    where = _nearest_existing(Path(directory)) if create else directory
    try:
        st = os.stat(where)
    except FileNotFoundError:
        raise UsageError(f"{named}: directory {shown_path(where)} does not exist") from None
    except NotADirectoryError:  # a file where the path goes on: name it
        raise UsageError(f"{named}: {shown_path(_nearest_existing(Path(where)))} is not a "
                         "directory") from None
    except (OSError, ValueError) as exc:  # a loop of links, no permission, a NUL byte, ...
        raise UsageError(f"{named}: directory {shown_path(where)}: "
                         f"{getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise UsageError(f"{named}: {shown_path(where)} is not a directory")
    if not os.access(where, os.W_OK | os.X_OK):
        raise UsageError(f"{named}: directory {shown_path(where)} is not writable")
    return st


def _place(out: Output) -> os.stat_result | None:
    """The status of an output file that exists (None: it does not yet), after checking
    that it can be written where it is."""
    shown = shown_path(out.path)
    try:
        st: os.stat_result | None = os.stat(out.path)
    except (FileNotFoundError, NotADirectoryError):  # the directory check says which part
        st = None
    except OSError as exc:  # a loop of links, no permission to look, ...
        raise UsageError(f"{out.option} {shown}: {exc.strerror or exc}") from None
    except ValueError as exc:  # an embedded NUL byte
        raise UsageError(f"{out.option} {shown}: not a usable path ({exc})") from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise UsageError(f"{out.option} {shown}: is a directory, not a regular file (give "
                         "the file's name)")
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise UsageError(f"{out.option} {shown}: is {file_kind(st.st_mode)}, not a "
                         "regular file")
    if st is not None and out.append:
        if not os.access(out.path, os.W_OK):
            raise UsageError(f"{out.option} {shown}: is not writable")
        return st
    _writable_directory(f"{out.option} {shown}", Path(os.path.abspath(out.path)).parent,
                        create=out.makes_directories)
    return st


def check_outputs(inputs: Iterable[Input], outputs: Sequence[Output], *,
                  force: bool = False) -> None:
    """Refuse, in one `UsageError` line, an output that is one of `inputs` or another
    output, one that cannot be written where it is, or (unless `force`) one that exists
    and was not written by motor-monitor. Call it before any work: nothing is opened for
    writing here."""
    named: dict[tuple[int, int], Input] = {}
    for option, path in inputs:
        key = _identity(path)
        if key is not None:
            named.setdefault(key, (option, path))
    seen: dict[object, Output] = {}
    existing: list[Output] = []
    for out in outputs:
        st = _place(out)
        ident: object
        if st is None:
            ident = os.path.realpath(out.path)
        else:
            ident = (st.st_dev, st.st_ino)
            existing.append(out)
            if ident in named:
                option, path = named[ident]
                raise UsageError(f"{_named(out.option, out.path)} is the same file as "
                                 f"{_named(option, path)}: an output never replaces an "
                                 f"input (name another file for {out.option})")
        other = seen.setdefault(ident, out)
        if other is not out:
            raise UsageError(f"{_named(other.option, other.path)} and "
                             f"{_named(out.option, out.path)} are the same file: each "
                             "output needs its own")
    if force:
        return
    for out in existing:
        if out.kind is not None and not is_own_file(out.path, out.kind):
            how = "append to" if out.append else "replace"
            raise UsageError(f"{_named(out.option, out.path)} exists and was not written by "
                             f"motor-monitor (it is not {_KINDS[out.kind][0]}); give --force "
                             f"to {how} it")


def check_directory(option: str, path: str | os.PathLike[str], inputs: Iterable[Input] = (),
                    *, create: bool = False, rotated: bool = False) -> None:
    """Refuse, in one `UsageError` line, an output directory that is not one, is not
    writable or (without `create`: the command makes it) does not exist; and, if the
    directory holds `rotated` files whose oldest are deleted, an input that lies in it
    with such a name."""
    shown = shown_path(path)
    if create:
        try:
            os.stat(path)
        except FileNotFoundError:  # the command makes it: its nearest ancestor must take it
            _writable_directory(f"{option} {shown}", Path(os.path.abspath(path)).parent,
                                create=True)
            return
        except (OSError, ValueError):
            pass  # refused below, in the words of any other directory
    st = _writable_directory(option, path, create=False)
    if not rotated:
        return
    for in_option, in_path in inputs:
        for candidate in {os.path.abspath(in_path), os.path.realpath(in_path)}:
            parent = _identity(os.path.dirname(candidate))
            if (parent == (st.st_dev, st.st_ino)
                    and _ROTATED_NAME.fullmatch(os.path.basename(candidate))):
                raise UsageError(f"{_named(in_option, in_path)} lies in {option} {shown} "
                                 "and is named like the rotated files whose oldest are "
                                 "deleted there: move it, or choose another directory")


# -- recognising the files motor-monitor wrote ---------------------------------------------


class _Probe:
    """Bounded reads of an open regular file."""

    def __init__(self, fd: int, size: int) -> None:
        self.fd = fd
        self.size = size

    def at(self, offset: int, n: int) -> bytes:
        return os.pread(self.fd, max(0, min(n, self.size - offset)), max(0, offset))

    def head(self, n: int = _HEAD) -> bytes:
        return self.at(0, n)

    def tail(self, n: int = _TAIL) -> bytes:
        return self.at(self.size - n, n)

    def first_line(self) -> bytes:
        return self.head().split(b"\n", 1)[0]


def _rig(p: _Probe) -> bool:
    return p.first_line().startswith(RIG_HEADER.encode())


def _thresholds(p: _Probe) -> bool:
    from monitor.diagnosis.thresholds import THRESHOLDS_HEADER

    return p.first_line().startswith(THRESHOLDS_HEADER.encode())


def _report(p: _Probe) -> bool:
    if p.size > _REPORT_LIMIT:
        return False
    try:
        doc = json.loads(p.head(p.size))
    except (UnicodeDecodeError, ValueError, RecursionError):
        return False
    capture = doc.get("capture") if isinstance(doc, dict) else None
    return isinstance(capture, dict) and "files" in capture


def _png(p: _Probe) -> bool:
    head = p.head(256)
    return head.startswith(PNG_MAGIC) and _MATPLOTLIB in head


def _is_event(line: bytes) -> bool:
    from monitor.pipeline.events import DiagnosisEvent, DriveEvent

    try:
        doc = json.loads(line)
    except (UnicodeDecodeError, ValueError, RecursionError):
        return False
    fields = {f.name for f in dataclasses.fields(DiagnosisEvent)}
    # also the lines of an older monitor (the fault named `fault_volts`, without its unit;
    # before that without the model-mismatch flag): `run --events` goes on appending to
    # such a file
    older = fields - {"fault_input", "fault_input_unit"} | {"fault_volts"}
    drive = set(json.loads(DriveEvent(0.0, "").to_json()))  # what a drive says (kind drive)
    return isinstance(doc, dict) and set(doc) in (fields, older,
                                                  older - {"model_mismatch", "kind"}, drive)


def _events(p: _Probe) -> bool:
    """The first and the last complete line are events (a last line cut short by a kill
    is left out: appending goes on after it)."""
    head = p.head(_TAIL)
    if b"\n" not in head:
        return False
    tail_lines = p.tail().split(b"\n")
    complete = tail_lines[:-1]  # what follows the last newline is cut short, or nothing
    return _is_event(head.split(b"\n", 1)[0]) and bool(complete) and _is_event(complete[-1])


def _rrd(p: _Probe) -> bool:
    return p.head(4) in RRD_MAGICS


def _metrics(p: _Probe) -> bool:
    from monitor.sinks.metrics import PREFIX

    return p.first_line().startswith(f"# HELP {PREFIX}_".encode())


def _column_names() -> list[bytes]:
    """The summary's first columns (log, node, status, ...): a summary an earlier version
    wrote, with fewer columns after them, is still ours."""
    from monitor.archive.summary import COLUMNS

    return [name.encode() for name, _ in COLUMNS[:5]]


def _summary_csv(p: _Probe) -> bool:
    return p.first_line().rstrip(b"\r").startswith(b",".join(_column_names()))


def _parquet_footer(p: _Probe) -> bytes | None:
    """The footer (schema and key-value metadata) of a Parquet file, None if not one."""
    end = p.tail(8)
    if p.head(4) != b"PAR1" or len(end) != 8 or end[4:] != b"PAR1":
        return None
    length = int.from_bytes(end[:4], "little")
    if not 0 < length <= min(_PARQUET_FOOTER_LIMIT, p.size - 12):
        return None
    return p.at(p.size - 8 - length, length)


def _summary_parquet(p: _Probe) -> bool:
    footer = _parquet_footer(p)
    return footer is not None and all(name in footer for name in _column_names())


def _samples_csv(p: _Probe) -> bool:
    from monitor.sinks.samples import CSV_FIRST, CSV_LAST

    line = p.first_line().rstrip(b"\r")
    return line.startswith(CSV_FIRST.encode()) and line.endswith(CSV_LAST.encode())


def _samples_parquet(p: _Probe) -> bool:
    from monitor.sinks.samples import PARQUET_KEY

    footer = _parquet_footer(p)
    return footer is not None and PARQUET_KEY in footer


_KINDS: dict[Kind, tuple[str, Callable[[_Probe], bool]]] = {
    "rig": ("a rig file motor-monitor identify wrote", _rig),
    "identify-report": ("a report motor-monitor identify wrote", _report),
    "png": ("a plot motor-monitor drew", _png),
    "thresholds": ("a thresholds file motor-monitor calibrate wrote", _thresholds),
    "events": ("JSON lines of motor-monitor's diagnosis events", _events),
    "rrd": ("a Rerun recording", _rrd),
    "metrics": ("motor-monitor's Prometheus metrics", _metrics),
    "summary-csv": ("an archive summary motor-monitor wrote", _summary_csv),
    "summary-parquet": ("an archive summary motor-monitor wrote", _summary_parquet),
    "samples-csv": ("a samples file motor-monitor wrote", _samples_csv),
    "samples-parquet": ("a samples file motor-monitor wrote", _samples_parquet),
}


def is_own_file(path: str | os.PathLike[str], kind: Kind) -> bool:
    """Whether the existing file at `path` is a `kind` of file motor-monitor writes, from a
    few KiB of its start and end: the first line of a rig file (`RIG_HEADER`), a thresholds
    file (`THRESHOLDS_HEADER`) or a metrics file; the first and last line of JSON lines of
    events; the magic bytes of a recording, a PNG plot (and matplotlib's mark) or a Parquet
    summary (and its columns) or samples file (and its key-value metadata key); a report's
    "capture" object; the header of a CSV summary or samples file.
    An empty file is taken as ours (replacing it loses nothing); a file that cannot be read
    is not."""
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError):
        return False
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return False
        if st.st_size == 0:
            return True
        return _KINDS[kind][1](_Probe(fd, st.st_size))
    except OSError:
        return False
    finally:
        os.close(fd)


# -- writing -------------------------------------------------------------------------------


def _cannot_write(option: str, path: str | os.PathLike[str], exc: OSError) -> MonitorError:
    # exc's own text names the temporary file: only its reason is shown
    return MonitorError(f"{_named(option, path)}: cannot write "
                        f"({exc.strerror or type(exc).__name__})")


def write_text(option: str, path: str | os.PathLike[str], text: str) -> None:
    """`text` (UTF-8) written to `path` atomically (`atomic_output`); a failure is one
    line naming `option` and `path`."""
    with atomic_output(option, path) as tmp:
        tmp.write_text(text, encoding="utf-8")


@contextlib.contextmanager
def atomic_output(option: str, path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside `path` with its suffix, renamed over `path` once the block
    has written it (`atomic_replace`); an OSError, of the block or of the rename, is one
    line naming `option` and `path`, and `path` stays as it was."""
    try:
        with atomic_replace(path) as tmp:
            yield tmp
    except OSError as exc:
        raise _cannot_write(option, path, exc) from None
