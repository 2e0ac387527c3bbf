"""`python -m focustrack_phase`: the phase service (REST and Zenoh)."""

from focustrack_phase.command import main

raise SystemExit(main())
