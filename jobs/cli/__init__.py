"""The `dncq` command, one module per command group. May import: anything of ours."""


def dncq() -> None:
    """Entry point of the `dncq` console script (jobs.cli.main is the command itself).

    Loading the command takes a moment, a command that runs the service seconds: a Ctrl-C
    meanwhile ends it as one later does (exit 130), not with a traceback of the imports it
    cut short.
    """
    try:
        from jobs.cli.main import main as command

        command()
    except KeyboardInterrupt:
        raise SystemExit(130) from None
