from mowerhw.cli import main

raise SystemExit(main())
