"""The error the command line reports as one line, without a traceback."""


class CLIError(Exception):
    """A usage error found by the command line itself (not by the library)."""


def say(lines: list[str]) -> None:
    """A command's result summary on stdout (the only place the tool writes to stdout)."""
    import sys

    sys.stdout.write("\n".join(lines) + "\n")
