"""Command-line options shared by the commands: the options every monitoring command has,
and what they build (the rig, the database, the configuration: `monitor.setup` from the
options' values). The argument types live in `monitor.runtime.argtypes`."""

from __future__ import annotations

import argparse
from dataclasses import fields

from monitor import setup
from monitor.bus.codec import MotorDatabase
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

__all__ = ["OneLineParser", "add_monitor_options", "add_rig_option", "database",
           "monitor_config", "nodes", "positive_float", "positive_int", "rate", "rig",
           "settings"]

Options = argparse.Namespace
"""The parsed command line."""


def add_monitor_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that monitors frames (run, replay)."""
    add_rig_option(p)
    p.add_argument("--dbc", default=None, help="DBC file (default: the rig's)")
    p.add_argument("--nodes", type=nodes, default=None,
                   help="nodes to monitor, e.g. 0,3 (default: the rig's, else all that send)")
    p.add_argument("--rate", type=rate, default=None,
                   help="the output message's nominal rate, Hz (default: the rig's)")
    p.add_argument("--thresholds", default=None, help="thresholds TOML (motor-monitor calibrate)")
    p.add_argument("--key", default=None, metavar="FILE",
                   help="SecOC key (32 or 64 hex digits, mode 0600): reject unauthenticated frames")
    p.add_argument("--rrd", default=None, help="record to this .rrd file")
    p.add_argument("--connect", default=None, metavar="URL",
                   help="stream to a Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy")


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
