"""Every rig-file mistake is refused with one line naming the file, the key and what is
wrong: the cases of tests/rig/mistakes.toml (any rig, units, our own bus, SecOC), each a
test rig with one change."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import pytest

from tests.support.dbc import REPO_DBC
from tests.support.paths import ROOT, TEST_RIGS
from tests.support.rig_files import rig_refusal, written_rig

MISTAKES: list[dict[str, Any]] = tomllib.loads(
    (Path(__file__).with_name("mistakes.toml")).read_text())["mistake"]

# a test rig: its file and the DBC copied beside it (None: it names ours by absolute path)
RIGS: dict[str, tuple[Path, Path | None]] = {
    "servo": (TEST_RIGS / "servo.toml", TEST_RIGS / "servo.dbc"),
    "twin": (TEST_RIGS / "twin.toml", TEST_RIGS / "twin.dbc"),
    "secure_drive": (TEST_RIGS / "secure_drive.toml", TEST_RIGS / "secure_drive.dbc"),
    "motor": (ROOT / "rigs" / "motor.toml", None),
}


def _changed(text: str, pairs: list[list[str]]) -> str:
    for old, new in pairs:
        old, new = old.replace("{dbc}", str(REPO_DBC)), new.replace("{dbc}", str(REPO_DBC))
        assert old in text, f"{old!r} is not in the rig: the case tests nothing"
        text = text.replace(old, new)
    return text


def test_the_table_is_read_whole() -> None:
    assert len(MISTAKES) >= 50 and {m["rig"] for m in MISTAKES} == set(RIGS)
    assert len({m["what"] for m in MISTAKES}) == len(MISTAKES)


@pytest.mark.parametrize("case", MISTAKES, ids=[m["what"] for m in MISTAKES])
def test_each_mistake_is_one_line(tmp_path: Path, case: dict[str, Any]) -> None:
    rig, dbc = RIGS[case["rig"]]
    text = rig.read_text().replace('"../dbc/motor.dbc"', f'"{REPO_DBC}"')
    if "text" in case:
        text = case["text"]
    text = _changed(text, case.get("replace", [])) + case.get("append", "")
    if dbc is not None:
        (tmp_path / dbc.name).write_text(_changed(dbc.read_text(), case.get("dbc_replace", [])))
    path = written_rig(tmp_path, text)
    msg = rig_refusal(path)
    line = case["line"].replace("{dbc}", str(REPO_DBC))
    assert msg.startswith(f"rig file {path}: {line}"), msg
    assert case.get("contains", "") in msg, msg
