"""`python -m jobs.cli`: the `dncq` command."""

from jobs.cli import dncq

dncq()
