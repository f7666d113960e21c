"""What a running process needs around the monitor, shared by the command line
(`monitor.app`) and the virtual ECU (`sim_ecu`): opening and using a CAN bus (`canbus`),
stopping on SIGINT/SIGTERM (`signals`), saving the SecOC freshness (`freshness`), telling
systemd its state (`notify`), checking a command's outputs before any work (`paths`) and the
argument types that refuse a bad value in one line (`argtypes`). Nothing here imports the
estimator (numba): `sim-ecu` starts without it."""
