"""`python -m focustrack_scheduler`: scan one slide through the services."""

from focustrack_scheduler.scan import main

raise SystemExit(main())
