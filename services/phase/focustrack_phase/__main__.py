"""`python -m focustrack_phase`: the phase service (REST)."""

from focustrack_phase.command import main

raise SystemExit(main())
