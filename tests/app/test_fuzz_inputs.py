"""Every file a user hands over, thrown at every file-taking option of every command.

Random bytes, random TOML values of each rig key's own type, FIFOs, devices, directories,
symbolic-link loops and huge files go to ``--rig``, ``--dbc``, ``--thresholds``, ``--key``,
the captures, the gamma^ file, ``status``'s metrics file and ``sim-ecu --scenario``. Each
command runs as its own process under a memory limit and a time limit, and must end in one
clear line (exit 2; 1 for a damaged log) or succeed, never in a traceback, a hang or an
exhausted memory; every input is byte-identical afterwards.

``FUZZ_EXAMPLES`` scales the hypothesis examples (default 1: a few minutes).
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
import resource
import subprocess
import tomllib
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.archive.logs import ecu_frames, write_log
from tests.support import BIN
from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT, TEST_RIGS

SCALE = max(1, int(os.environ.get("FUZZ_EXAMPLES", "1")))
TIME_LIMIT_S = 90.0  # a refusal takes ~2 s; a hang is anything near this
MEMORY_LIMIT = 6 * 2**30  # address space: numba and LLVM reserve ~3 GiB; far below the machine
HUGE = 2 * 2**30  # a sparse file far larger than any rig, key or metrics file may be



def fuzz(examples: int) -> settings:
    """Hypothesis settings of these tests: reproducible, no deadline (each example is a
    process of its own), `examples` times FUZZ_EXAMPLES examples."""
    return settings(max_examples=examples * SCALE, deadline=None, derandomize=True,
                    database=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                          HealthCheck.too_slow])


@dataclass(frozen=True)
class Outcome:
    argv: tuple[str, ...]
    returncode: int
    stderr: tuple[str, ...]
    timed_out: bool

    def describe(self) -> str:
        shown = [*self.stderr[:1], *self.stderr[-4:]]  # a traceback's start and its end
        return f"{' '.join(self.argv)} -> {self.returncode}: {shown}"


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def run_command(argv: Sequence[str], cwd: Path) -> Outcome:
    """`argv` (program name first) as its own process, bounded in memory and time."""
    exe = str(BIN / argv[0])
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    try:
        proc = subprocess.run([exe, *argv[1:]], capture_output=True, text=True, errors="replace",
                              timeout=TIME_LIMIT_S, cwd=cwd, env=env,
                              stdin=subprocess.DEVNULL, preexec_fn=_limit_memory)
    except subprocess.TimeoutExpired:
        return Outcome(tuple(argv), -9, (), True)
    lines = tuple(ln for ln in proc.stderr.splitlines() if ln.strip())
    return Outcome(tuple(argv), proc.returncode, lines, False)


def _digests(paths: Sequence[Path]) -> dict[Path, str]:
    out = {}
    for p in paths:
        if p.is_file() and not p.is_symlink() and p.stat().st_size < 2**28:
            out[p] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def assert_refused_or_fine(out: Outcome, *, codes: Sequence[int] = (2,),
                           allow_success: bool = False, names: str | None = None) -> None:
    """No hang, no traceback, no death by signal or memory; a refusal is one line."""
    assert not out.timed_out, f"hung for {TIME_LIMIT_S:.0f} s: {out.describe()}"
    assert not any("Traceback" in ln for ln in out.stderr), out.describe()
    assert out.returncode >= 0, f"killed by signal {-out.returncode}: {out.describe()}"
    if out.returncode == 0 and allow_success:
        return
    assert out.returncode in codes, out.describe()
    errors = [ln for ln in out.stderr if ": error: " in ln]
    assert len(errors) == 1 and errors[0] == out.stderr[-1], out.describe()
    assert len(errors[0]) <= 600, f"an error line of {len(errors[0])} characters"
    if names is not None:
        assert names in errors[0], out.describe()


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with a short healthy capture of our bus and a valid file of each kind."""
    d = tmp_path_factory.mktemp("fuzz")
    write_log(d / "cap.log", ecu_frames(["healthy"], duration=2.0))
    (d / "rig.toml").write_text((ROOT / "rigs" / "motor.toml").read_text().replace(
        '"../dbc/motor.dbc"', f'"{REPO_DBC}"'))
    (d / "thresholds.toml").write_text('quantity = "gamma"\nf1 = 0.1\nf2 = 0.8\n')
    key = d / "secoc.key"
    key.write_text("00" * 16 + "\n")
    key.chmod(0o600)
    return d


# --- every file-taking option of every command -------------------------------------------

Slot = tuple[str, tuple[str, ...], tuple[int, ...]]
"""(name, argv with {} where the file goes, the exit codes a refusal may have)."""


def slots(d: Path) -> list[Slot]:
    cap, rig = str(d / "cap.log"), str(d / "rig.toml")
    virtual = ("--interface", "virtual", "--channel", "fuzz")
    ecu = ("sim-ecu", *virtual, "--node", "0", "--duration", "0.2")
    return [
        ("replay --rig", ("motor-monitor", "replay", cap, "--rig", "{}", "--events",
                          str(d / "o.jsonl")), (2,)),
        ("replay --dbc", ("motor-monitor", "replay", cap, "--dbc", "{}"), (2,)),
        ("replay --thresholds", ("motor-monitor", "replay", cap, "--thresholds", "{}"), (2,)),
        ("replay --key", ("motor-monitor", "replay", cap, "--key", "{}"), (2,)),
        ("replay LOG", ("motor-monitor", "replay", "{}"), (1, 2)),
        ("identify --rig", ("motor-monitor", "identify", cap, "--rig", "{}", "--out",
                            str(d / "learned.toml")), (1, 2)),
        ("identify CAPTURE", ("motor-monitor", "identify", "{}", "--out",
                              str(d / "learned.toml")), (1, 2)),
        ("calibrate --rig", ("motor-monitor", "calibrate", cap, "--rig", "{}", "--out",
                             str(d / "th.toml")), (1, 2)),
        ("calibrate GAMMA", ("motor-monitor", "calibrate", "{}", "--out", str(d / "th.toml")),
         (1, 2)),
        ("status FILE", ("motor-monitor", "status", "{}"), (2,)),
        ("run --rig", ("motor-monitor", "run", *virtual, "--rig", "{}"), (2,)),
        ("run --thresholds", ("motor-monitor", "run", *virtual, "--rig", rig,
                              "--thresholds", "{}"), (2,)),
        ("run --key", ("motor-monitor", "run", *virtual, "--key", "{}"), (2,)),
        ("sim-ecu --scenario", (*ecu, "--scenario", "{}"), (2,)),
        ("sim-ecu --rig", (*ecu, "--scenario", "healthy", "--rig", "{}"), (2,)),
    ]


def _put(argv: tuple[str, ...], path: Path) -> tuple[str, ...]:
    return tuple(str(path) if a == "{}" else a for a in argv)


SPECIALS = ("fifo", "device", "directory", "symlink_loop", "huge", "missing_parent")


def _special(kind: str, d: Path, suffix: str) -> Path:
    if kind == "fifo":
        p = d / f"fifo{suffix}"
        if not p.exists():
            os.mkfifo(p)
        return p
    if kind == "device":
        return Path("/dev/zero")
    if kind == "directory":
        p = d / f"adir{suffix}"
        p.mkdir(exist_ok=True)
        return p
    if kind == "symlink_loop":
        a, b = d / f"loop_a{suffix}", d / f"loop_b{suffix}"
        if not a.is_symlink():
            a.symlink_to(b)
            b.symlink_to(a)
        return a
    if kind == "huge":
        p = d / f"huge{suffix}"
        with open(p, "wb") as fh:
            fh.truncate(HUGE)
        return p
    return d / "no" / "such" / f"file{suffix}"


def _suffix(name: str) -> str:
    if "LOG" in name or "CAPTURE" in name:
        return ".log"
    if "status" in name:
        return ".prom"
    if "GAMMA" in name:
        return ".txt"
    if "dbc" in name:
        return ".dbc"
    if "key" in name:
        return ".key"
    return ".toml"


def _slot_ids() -> list[str]:
    return [s[0] for s in slots(Path("/x"))]


@pytest.mark.parametrize("slot", _slot_ids())
def test_special_files_refused_in_one_line(work: Path, slot: str) -> None:
    """A FIFO never blocks, /dev/zero and a huge file are never read to the end, a
    directory or a loop is called what it is: one line naming the file, bounded time and
    memory (the kinds run two at a time, one per core)."""
    name, argv, codes = next(s for s in slots(work) if s[0] == slot)
    kinds = [k for k in SPECIALS
             # a capture may be as large as a disk: its size is no mistake; a directory of
             # logs is an archive (its own tests)
             if not (k == "huge" and codes != (2,))
             and not (k == "directory" and name == "replay LOG")]
    inputs = [work / "cap.log", work / "rig.toml", work / "thresholds.toml"]
    before = _digests(inputs)

    def probe(kind: str) -> tuple[str, Path, Outcome]:
        d = work / f"special-{kind}-{name.replace(' ', '_')}"
        d.mkdir(exist_ok=True)
        path = _special(kind, d, _suffix(name))
        try:
            return kind, path, run_command(_put(argv, path), work)
        finally:
            if kind == "huge":
                path.unlink(missing_ok=True)

    with ThreadPoolExecutor(max_workers=2) as pool:
        outcomes = list(pool.map(probe, kinds))
    for kind, path, out in outcomes:
        try:
            assert_refused_or_fine(out, codes=codes, names=path.name)
        except AssertionError as exc:
            raise AssertionError(f"{kind}: {exc}") from None
    assert _digests(inputs) == before


# --- random bytes ----------------------------------------------------------------------

@fuzz(30)
@given(slot=st.sampled_from([s for s in _slot_ids() if s != "run --key"]),
       data=st.one_of(st.binary(max_size=600),
                      st.text(max_size=400).map(lambda s: s.encode("utf-8", "surrogatepass"))))
def test_random_bytes_refused_in_one_line(work: Path, slot: str, data: bytes) -> None:
    name, argv, codes = next(s for s in slots(work) if s[0] == slot)
    d = work / "bytes"
    d.mkdir(exist_ok=True)
    path = d / f"random{_suffix(name)}"
    path.write_bytes(data)
    path.chmod(0o600)
    before = _digests([path, work / "cap.log", work / "rig.toml"])
    out = run_command(_put(argv, path), work)
    # Random bytes may happen to be a valid key (16 or 32 raw bytes; `run --key` is left
    # out, as a valid key would start the daemon): a success is allowed where the file is
    # valid, except for `run`, which would not return.
    assert_refused_or_fine(out, codes=codes, allow_success=not name.startswith("run"))
    assert _digests([path, work / "cap.log", work / "rig.toml"]) == before


# --- random TOML values of each key's own type -------------------------------------------

def _leaves(doc: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[tuple[Any, ...], Any]]:
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, (*prefix, k))
    elif isinstance(doc, list) and doc and all(isinstance(x, (dict, list)) for x in doc):
        for i, v in enumerate(doc):
            yield from _leaves(v, (*prefix, i))
    else:
        yield prefix, doc


def _set(doc: Any, path: tuple[Any, ...], value: Any) -> None:
    for k in path[:-1]:
        doc = doc[k]
    doc[path[-1]] = value


NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-308, 1e308, -1e308, 1e-100, 1e-6, 1e6, 5e-324, -35.0]),
    st.integers(min_value=-2**63, max_value=2**63 - 1),
)


def _value_like(example: Any) -> st.SearchStrategy[Any]:
    """A random value of `example`'s TOML type (numbers any number, arrays of its rows)."""
    if isinstance(example, bool):
        return st.booleans()
    if isinstance(example, (int, float)):
        return NUMBERS
    if isinstance(example, str):
        return st.one_of(st.text(max_size=40), st.sampled_from(
            ["", "mA", "kg", "trun/s", "V", "NoSuchSignal", "id_bits", "x" * 5000]))
    if isinstance(example, list):
        row = example[0] if example else 0.0
        return st.lists(_value_like(row), max_size=6)
    return st.just(example)


RIG_SOURCES = {
    "motor": ROOT / "rigs" / "motor.toml",
    "servo": TEST_RIGS / "servo.toml",
}


@st.composite
def mutated_rig(draw: st.DrawFn) -> tuple[str, dict[str, Any]]:
    which = draw(st.sampled_from(sorted(RIG_SOURCES)))
    doc = tomllib.loads(RIG_SOURCES[which].read_text())
    leaves = list(_leaves(doc))
    for _ in range(draw(st.integers(1, 3))):
        path, example = draw(st.sampled_from(leaves))
        if path[:2] == ("bus", "dbc"):
            continue  # the DBC's path: the random-bytes test covers the DBC itself
        _set(doc, path, draw(_value_like(example)))
    return which, doc


@fuzz(40)
@given(rig=mutated_rig())
def test_random_rig_values_never_crash(work: Path, rig: tuple[str, dict[str, Any]]) -> None:
    """A rig whose values are random but of the right type: replayed, or refused in one
    line naming the rig file, never a traceback; the capture untouched."""
    which, drawn = rig
    doc = copy.deepcopy(drawn)  # hypothesis shows the drawn value when it reports
    source = RIG_SOURCES[which]
    for k in ("bus",):  # DBC paths are relative to the rig file: make them absolute
        dbc = doc.get(k, {}).get("dbc")
        if isinstance(dbc, str):
            doc[k]["dbc"] = str((source.parent / dbc).resolve())
        elif isinstance(dbc, list):
            doc[k]["dbc"] = [str((source.parent / p).resolve()) if isinstance(p, str) else p
                             for p in dbc]
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):
        return  # not representable in TOML (e.g. a mixed array): no user can write it
    d = work / "rigs"
    d.mkdir(exist_ok=True)
    path = d / f"{which}.toml"
    path.write_text(text)
    before = _digests([work / "cap.log", path])
    out = run_command(("motor-monitor", "replay", str(work / "cap.log"), "--rig", str(path),
                       "--events", str(d / "ev.jsonl")), work)
    assert_refused_or_fine(out, codes=(1, 2), allow_success=True)
    if out.returncode == 2:
        assert path.name in out.stderr[-1] or "--rig" in out.stderr[-1], out.describe()
    assert _digests([work / "cap.log", path]) == before


@fuzz(10)
@given(f1=NUMBERS, f2=NUMBERS, quantity=st.sampled_from(["gamma", "fault_volts", ""]),
       centres=st.lists(NUMBERS, max_size=4))
def test_random_threshold_values_never_crash(work: Path, f1: Any, f2: Any, quantity: str,
                                             centres: list[Any]) -> None:
    d = work / "thr"
    d.mkdir(exist_ok=True)
    path = d / "t.toml"
    path.write_text(tomli_w.dumps({"quantity": quantity, "f1": f1, "f2": f2,
                                   "centres": centres}))
    out = run_command(("motor-monitor", "replay", str(work / "cap.log"), "--thresholds",
                       str(path), "--events", str(d / "ev.jsonl")), work)
    valid = (quantity == "gamma" and all(isinstance(v, (int, float)) and math.isfinite(v)
                                         for v in (f1, f2)) and 0 < f1 < f2 < 1)
    assert_refused_or_fine(out, codes=(2,), allow_success=valid)
    if not valid:
        assert "t.toml" in out.stderr[-1], out.describe()


def test_fuzz_runs_the_real_commands(work: Path) -> None:
    """The harness itself: a valid replay succeeds and a missing rig is one line, so the
    tests above can tell a refusal from a success."""
    ok = run_command(("motor-monitor", "replay", str(work / "cap.log"), "--rig",
                      str(work / "rig.toml"), "--events", str(work / "ok.jsonl")), work)
    assert ok.returncode == 0, ok.describe()
    bad = run_command(("motor-monitor", "replay", str(work / "cap.log"), "--rig",
                       str(work / "nope.toml")), work)
    assert_refused_or_fine(bad, names="nope.toml")
