"""`python -m focustrack_estimator`: the estimator REST service."""

from focustrack_estimator.service import main

raise SystemExit(main())
