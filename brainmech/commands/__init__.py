"""The subcommands, one module each, in the order ``brainmech --help`` lists them.

A new subcommand is one module with ``add(subparsers)`` (its options, ending in
``set_defaults(run=run)``) and ``run(args) -> exit code``, and one line below."""

from . import (
    benchmark_diagnosis,
    brain_bank,
    diagnose,
    identify,
    import_exports,
    reproduce,
    sample,
    simulate,
    train,
)

COMMANDS = (simulate, sample, train, identify, brain_bank, reproduce, diagnose,
            benchmark_diagnosis, import_exports)
