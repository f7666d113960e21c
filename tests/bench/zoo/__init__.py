"""Helpers of the rig zoo (`python -m tests.bench.rig_zoo`): random plants, buses, scoring.

Nothing here imports `monitor` or `sim_ecu`: the zoo talks to the product only through the
`motor-monitor` command line.
"""
