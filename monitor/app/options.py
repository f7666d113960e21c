"""What the commands' shared options build: the rig, the frame decoder, the monitor's
configuration (`monitor.setup` from the options' values). The options themselves and their
argument types live in `monitor.runtime.argtypes`, which imports nothing heavy: the daemon
parses its command line and opens its socket before it loads the estimator."""

from __future__ import annotations

import argparse
from dataclasses import fields

from monitor import setup
from monitor.bus.codec import MotorDatabase
from monitor.bus.logfile import suffix_list
from monitor.bus.rigcodec import RigCodec
from monitor.pipeline import MonitorConfig
from monitor.rig import Rig
from monitor.runtime.argtypes import (
    OneLineParser,
    add_rig_option,
    nodes,
    positive_float,
    positive_int,
    rate,
)

__all__ = ["OneLineParser", "add_captures_and_rig", "add_rig_option", "database",
           "monitor_config", "nodes", "positive_float", "positive_int", "rate", "rig", "settings"]

Options = argparse.Namespace
"""The parsed command line."""


def add_captures_and_rig(p: argparse.ArgumentParser, *, nargs: str, what: str) -> None:
    """The captures a command holds against a rig whose model may be missing yet (check,
    identify): CAPTURE... (`what` describes them; ``{formats}`` in it becomes the formats
    read) and --rig."""
    p.add_argument("captures", nargs=nargs, metavar="CAPTURE",
                   help=what.format(formats=f"({suffix_list()})"))
    add_rig_option(p, model_optional=True)


def settings(args: Options) -> setup.MonitorSettings:
    """The options that configure the monitor, as plain values (`monitor.setup`); those
    `args` lacks are None."""
    return setup.MonitorSettings(**{f.name: getattr(args, f.name, None)
                                    for f in fields(setup.MonitorSettings)})


def rig(args: Options, *, model_optional: bool = False) -> Rig:
    """--rig, else the built-in rig; --dbc replaces its DBC files. `model_optional`: a rig
    file without [model] is taken (`load_rig`), for the command that learns one."""
    return setup.setup_rig(getattr(args, "rig", None), dbc=getattr(args, "dbc", None),
                           model_optional=model_optional)


def database(args: Options, the_rig: Rig | None = None) -> MotorDatabase | RigCodec:
    """The rig's frame decoder, with SecOC verification when --key is given (a key file
    only we can read; our own bus, or a rig whose messages have SecOC)."""
    return setup.frame_decoder(the_rig or rig(args), getattr(args, "key", None))


def monitor_config(args: Options, the_rig: Rig | None = None) -> MonitorConfig:
    """The monitor's configuration: the rig's, with the command line's overrides."""
    return setup.monitor_config(the_rig or rig(args), nodes=getattr(args, "nodes", None),
                                rate=getattr(args, "rate", None),
                                thresholds=getattr(args, "thresholds", None))
