from focustrack.cli import main

raise SystemExit(main())
