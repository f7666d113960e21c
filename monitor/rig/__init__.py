"""The rig in front of the monitor, described by a TOML file: the bus (DBC files, how a
frame belongs to a node, which signals are the model's inputs and outputs, each message's
protection), the plant model of every node and the diagnosis settings. `load_rig` reads and
checks a file, `builtin_rig` is our own bus and the paper's motor (rigs/motor.toml);
`build_decoder` and `build_model` make what the monitor runs with."""

from monitor.rig.check import build_decoder, build_model, is_builtin_bus
from monitor.rig.load import RigError, builtin_rig, load_rig, model_of, parse_rig
from monitor.rig.spec import Rig

__all__ = ["Rig", "RigError", "build_decoder", "build_model", "builtin_rig", "is_builtin_bus",
           "load_rig", "model_of", "parse_rig"]
