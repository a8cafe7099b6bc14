"""`python -m jobs.cli`: the `dncq` command."""

from jobs.cli.main import main

main()
