"""The rig's errors and the rules the loader (`monitor.rig.load`) and the checks against the
DBC and the model (`monitor.rig.check`) share, in a module of their own so that neither
imports the other for them."""

from __future__ import annotations

from monitor.errors import MonitorError

__all__ = ["NO_MODEL", "RigError"]


class RigError(MonitorError, ValueError):
    """A rig file that cannot serve (one line: file, key, problem)."""


NO_MODEL = ("missing: the rig has no model yet; learn it from a healthy capture with "
            "motor-monitor identify CAPTURE --rig RIG --out LEARNED.toml, then give "
            "--rig LEARNED.toml")
"""What is wrong with a rig without [model] wherever a model is needed."""
