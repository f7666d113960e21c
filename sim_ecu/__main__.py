"""``python -m sim_ecu``: the ``sim-ecu`` command."""

from sim_ecu.cli import main

raise SystemExit(main())
