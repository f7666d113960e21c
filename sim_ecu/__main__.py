"""``python -m sim_ecu``: the ``sim-ecu`` command."""

from sim_ecu.program import main

raise SystemExit(main())
