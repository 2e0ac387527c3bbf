"""`python -m focustrack_focus`: the focus service (Zenoh and REST)."""

from focustrack_focus.command import main

raise SystemExit(main())
