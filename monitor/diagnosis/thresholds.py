"""Thresholds F1 < F2 of eq (76) and their TOML file, and the diagnosis' settings a rig file
gives (`DiagnosisSpec`)."""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from monitor.errors import MonitorError, one_line
from monitor.files import KIB, UserFileError, atomic_write_text, read_user_toml, shown_path

__all__ = ["DEFAULT_THRESHOLDS", "THRESHOLDS_HEADER", "DiagnosisError", "DiagnosisSpec",
           "Thresholds", "load_thresholds", "save_thresholds"]


THRESHOLDS_FILE_LIMIT = 64 * KIB
"""The largest thresholds file read: a few keys and the cluster centres fit in a few
hundred bytes."""


class DiagnosisError(MonitorError, ValueError):
    """Bad clustering input, bad thresholds or a bad thresholds file (one-line message)."""


def _finite_number(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise DiagnosisError(f"{name} must be a number, got {type(value).__name__}")
    try:
        out = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise DiagnosisError(f"{name} must be finite, got an integer too large for a "
                             "number") from None
    if not math.isfinite(out):
        raise DiagnosisError(f"{name} must be finite, got {out!r}")
    return out


@dataclass(frozen=True)
class Thresholds:
    """Thresholds F1 < F2 of eq (76) on `quantity` (default gamma^, the loss of effectiveness).

    `centres` records the sorted cluster centres they came from (empty for hand-set ones).
    """

    f1: float
    f2: float
    quantity: str = "gamma"
    centres: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        f1 = _finite_number("f1", self.f1)
        f2 = _finite_number("f2", self.f2)
        if not f1 < f2:
            raise DiagnosisError(f"f1 ({f1!r}) must be less than f2 ({f2!r})")
        if not isinstance(self.quantity, str) or not self.quantity.strip():
            raise DiagnosisError("quantity must be a non-empty string")
        if self.quantity == "gamma" and not 0.0 < f1 < f2 < 1.0:
            # gamma^ lies in [0, 1]: outside, a region (76) could never be reported
            raise DiagnosisError(f"gamma thresholds must satisfy 0 < f1 < f2 < 1, "
                                 f"got f1 = {f1!r}, f2 = {f2!r}")
        try:
            centres = tuple(_finite_number(f"centres[{i}]", c) for i, c in enumerate(self.centres))
        except TypeError as exc:
            raise DiagnosisError("centres must be a sequence of numbers") from exc
        if any(b <= a for a, b in itertools.pairwise(centres)):
            raise DiagnosisError("centres must be strictly increasing")
        object.__setattr__(self, "f1", f1)
        object.__setattr__(self, "f2", f2)
        object.__setattr__(self, "centres", centres)


DEFAULT_THRESHOLDS = Thresholds(f1=0.15, f2=0.85, quantity="gamma")
"""Hand-set gamma thresholds used when no calibrated thresholds file is given.

Typical gamma^ clusters are fault-free at 0, a partial fault somewhere in 0.3-0.7 and an
outage at 1. The equal-membership midpoints are then F1 in [0.15, 0.35] and F2 in
[0.65, 0.85]; F1 = 0.15 = (0 + 0.3)/2 and F2 = 0.85 = (0.7 + 1)/2 are the widest choice, so
every partial fault in that range is reported as a fault and not confused with fault-free
or outage. The monitor uses calibrated thresholds (`calibrate`, `load_thresholds`) when a
file is given. The paper's F1 = 0.3, F2 = 1 are in its f^ units and do not apply here.
"""


@dataclass(frozen=True)
class DiagnosisSpec:
    """Thresholds (76), debouncing and timeouts of the online diagnosis: a rig file's
    ``[diagnosis]`` (`monitor.rig.spec.Rig.diagnosis`), and with its defaults those of
    `monitor.pipeline.MonitorConfig`, which takes them from here."""

    f1: float = DEFAULT_THRESHOLDS.f1
    f2: float = DEFAULT_THRESHOLDS.f2
    dwell_s: float = 0.03
    hysteresis: float = 0.02
    significance: float = 0.75  # `monitor.diagnosis.rules.cls_update`
    silence_timeout_s: float = 0.5
    mismatch_window_s: float = 2.0
    mismatch_dwell_s: float = 3.0
    withhold_alarms_on_mismatch: bool = False  # `monitor.diagnosis.reported_state`


def _toml_string(value: str) -> str:
    out = ['"']
    for ch in value:
        code = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ch == "\r":
            out.append("\\r")
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04X}")
        elif 0xD800 <= code <= 0xDFFF:  # lone surrogate: not representable in TOML
            out.append("\\uFFFD")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def _toml_float(value: float) -> str:
    text = repr(float(value))  # shortest round-trip form; valid TOML for finite floats
    if text in ("inf", "-inf", "nan"):
        raise DiagnosisError(f"cannot write non-finite value {text}")
    return text


THRESHOLDS_HEADER = "# motor-monitor diagnosis thresholds"
"""How a thresholds file `save_thresholds` wrote begins: `calibrate` replaces a file that
begins so without --force (`monitor.runtime.paths`)."""


def save_thresholds(
    path: str | os.PathLike[str], thresholds: Thresholds, *, source: str = ""
) -> None:
    """Write `thresholds` as a small TOML file (atomically: temporary file, then rename).

    Keys: quantity, f1, f2, centres, source (free text, e.g. the run it was calibrated on)
    and created (UTC offset date-time). Read back with `load_thresholds`. A file that
    cannot be written is one `DiagnosisError` line naming `path`.
    """
    path = Path(path)
    created = datetime.now(UTC).isoformat(timespec="seconds")
    centres = ", ".join(_toml_float(c) for c in thresholds.centres)
    text = (
        f"{THRESHOLDS_HEADER}, eq (76) of Liu et al. 2020\n"
        "# fault-free: value < f1; fault: f1 <= value <= f2; outage: value > f2\n"
        f"quantity = {_toml_string(thresholds.quantity)}\n"
        f"f1 = {_toml_float(thresholds.f1)}\n"
        f"f2 = {_toml_float(thresholds.f2)}\n"
        f"centres = [{centres}]\n"
        f"source = {_toml_string(source)}\n"
        f"created = {created}\n"
    )
    try:
        atomic_write_text(path, text)
    except OSError as exc:  # its message would name the temporary file
        raise DiagnosisError(f"thresholds file {shown_path(path)}: cannot write "
                             f"({exc.strerror or type(exc).__name__})") from None


def load_thresholds(path: str | os.PathLike[str], *, quantity: str = "gamma") -> Thresholds:
    """Read thresholds written by `save_thresholds` (or by hand).

    Required keys: quantity (must equal `quantity`), f1, f2; optional: centres, source,
    created. Any problem (missing or unreadable file, invalid TOML, missing key, non-number,
    non-finite value, f1 >= f2, wrong quantity) raises DiagnosisError with one line naming
    the file and the problem.
    """
    what = "thresholds file"

    def fail(problem: str) -> DiagnosisError:
        return DiagnosisError(one_line(f"{what} {shown_path(path)}: {problem}", limit=500))

    try:
        doc = read_user_toml(path, what=what, limit=THRESHOLDS_FILE_LIMIT)
    except UserFileError as exc:
        raise DiagnosisError(str(exc)) from None
    for key in ("quantity", "f1", "f2"):
        if key not in doc:
            raise fail(f"missing key '{key}'")
    found = doc["quantity"]
    if not isinstance(found, str):
        raise fail(f"quantity must be a string, got {type(found).__name__}")
    if found != quantity:
        shown = found if len(found) <= 40 else found[:37] + "..."
        raise fail(f"thresholds are for quantity '{shown}', expected '{quantity}'")
    centres = doc.get("centres", [])
    if not isinstance(centres, list):
        raise fail(f"centres must be an array, got {type(centres).__name__}")
    try:
        return Thresholds(f1=doc["f1"], f2=doc["f2"], quantity=found, centres=tuple(centres))
    except DiagnosisError as exc:
        raise fail(str(exc)) from None


