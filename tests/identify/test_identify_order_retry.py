"""A black box whose order the data chose and whose replay fails is tried one order up,
through every refusal, and written where that serves; the report says which order was
refused and why (the rig zoo's seed 308: a first-order plant whose input frames arrive half
an output period after the output's: order 1 fits the hold-out about as well as order 2,
but the input arriving part way through a period is a fractional delay, and gamma^ reached
0.225 on the healthy capture; order 2 holds it). A given --order is never changed."""

from __future__ import annotations

import json
from pathlib import Path

from tests.support.identify import identify_zoo_rig, run_identify


def _report(out: Path) -> dict[str, object]:
    report = json.loads(out.with_suffix(".identify.json").read_text())
    assert isinstance(report, dict)
    return report


def test_the_chosen_order_that_fails_its_replay_is_tried_one_up(tmp_path: Path) -> None:
    res, report = identify_zoo_rig(308, tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert report["order"] == 2
    assert report["order_retry"] == {"order": 1, "failed": ["replay_gamma_margin"]}
    assert "FAIL" not in res.stdout

    given = tmp_path / "given.toml"
    res = run_identify("identify.log", "--rig", "rig.toml", "--out", given.name, "--node",
                       str(report["capture"]["node"]), "--order", "1", cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "replay_gamma_margin" in res.stderr and not given.exists()
    assert "order_retry" not in _report(given)
