"""`python -m diffshade` runs the command line (diffshade.cli)."""

from diffshade.cli import main

raise SystemExit(main())
