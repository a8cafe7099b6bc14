"""The `dncq` command, one module per command group. May import: anything of ours."""
