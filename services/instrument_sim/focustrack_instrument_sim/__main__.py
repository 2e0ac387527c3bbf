"""`python -m focustrack_instrument_sim`: the simulated microscope on Zenoh."""

from focustrack_instrument_sim.service import main

raise SystemExit(main())
