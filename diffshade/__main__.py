"""`python -m diffshade` runs the command line (diffshade.cli.program)."""

from diffshade.cli import program

raise SystemExit(program())
