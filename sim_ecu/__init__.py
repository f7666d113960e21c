"""Virtual motor ECU for hardware-in-the-loop runs of the monitor (``sim-ecu``)."""

from sim_ecu.ecu import ECUError, ECUStats, VirtualECU, load_motor_parameters, motor_parameters

__all__ = ["ECUError", "ECUStats", "VirtualECU", "load_motor_parameters", "motor_parameters"]
