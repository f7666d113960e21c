"""Virtual motor ECU for hardware-in-the-loop runs of the monitor (``sim-ecu``): the ECU of our
own bus (`sim_ecu.ecu.VirtualECU`), the twin of a user's rig (`sim_ecu.rig_ecu`), a CiA 402
drive (`sim_ecu.cia402`), the plant and scenarios they simulate, the command line
(`sim_ecu.cli`). Importing the package imports none of them: the program (`sim_ecu.program`)
decides what python-can loads before anything imports it."""
