"""`python -m focustrack_phase`: the phase service (REST)."""

from focustrack_phase.service import main

raise SystemExit(main())
