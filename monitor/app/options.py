"""Command-line options shared by the commands: argument types (each refuses a bad value
with one line naming it), the options every monitoring command has, and what they build
(the database, the configuration). The argument types live in `monitor.app.argtypes`."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from monitor.app.argtypes import OneLineParser, nodes, positive_float, positive_int, rate
from monitor.bus.codec import MotorDatabase
from monitor.bus.rigcodec import RigCodec
from monitor.bus.secoc import load_key
from monitor.diagnosis import Thresholds, load_thresholds
from monitor.estimation.fuzzy_ukf import FuzzyUKFConfig
from monitor.pipeline import MonitorConfig
from monitor.rig import Rig, build_decoder, build_model, builtin_rig, load_rig, model_of

__all__ = ["OneLineParser", "add_monitor_options", "add_rig_option", "database",
           "monitor_config", "nodes", "positive_float", "positive_int", "rate", "rig"]


def add_rig_option(p: argparse.ArgumentParser, *, model_optional: bool = False) -> None:
    """--rig; `model_optional`: the command learns the model (`rig(args, model_optional=True)`
    takes a rig file without [model])."""
    what = ("your DBC, node layout and signals; its [model], if any, is replaced"
            if model_optional else "your DBC, node layout, signals and model")
    p.add_argument("--rig", default=None, metavar="FILE",
                   help=f"rig file: {what} (default: our bus and the paper's motor, "
                   "rigs/motor.toml)")


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


def rig(args: argparse.Namespace, *, model_optional: bool = False) -> Rig:
    """--rig, else the built-in rig; --dbc replaces its DBC files. `model_optional`: a rig
    file without [model] is taken (`load_rig`), for the command that learns one."""
    found = (load_rig(args.rig, model_optional=model_optional) if getattr(args, "rig", None)
             else builtin_rig())
    dbc = getattr(args, "dbc", None)
    return replace(found, dbc=(Path(dbc),)) if dbc else found


def database(args: argparse.Namespace, the_rig: Rig | None = None) -> MotorDatabase | RigCodec:
    """The rig's frame decoder, with SecOC verification when --key is given (a key file
    only we can read; our own bus, or a rig whose messages have SecOC)."""
    key = load_key(args.key) if getattr(args, "key", None) else None
    return build_decoder(the_rig or rig(args), secoc_key=key)


def monitor_config(args: argparse.Namespace, the_rig: Rig | None = None) -> MonitorConfig:
    """The monitor's configuration: the rig's, with the command line's overrides."""
    r = the_rig or rig(args)
    spec, rig_rate = model_of(r)  # a rig still without a model: one line, identify first
    d = r.diagnosis
    thresholds = (load_thresholds(args.thresholds) if getattr(args, "thresholds", None)
                  else Thresholds(d.f1, d.f2))
    return MonitorConfig(
        nodes=args.nodes if getattr(args, "nodes", None) is not None else r.nodes,
        rate=args.rate if getattr(args, "rate", None) is not None else rig_rate,
        thresholds=thresholds, dwell_s=d.dwell_s, hysteresis=d.hysteresis,
        silence_timeout_s=d.silence_timeout_s, model=build_model(r),
        mismatch_window_s=d.mismatch_window_s, mismatch_dwell_s=d.mismatch_dwell_s,
        withhold_alarms_on_mismatch=d.withhold_alarms_on_mismatch,
        input_delay=spec.input_delay,
        estimator=FuzzyUKFConfig(adaptive_noise=spec.adaptive_noise,
                                 noise_window=spec.noise_window_s))
