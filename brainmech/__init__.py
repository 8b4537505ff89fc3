"""``brainmech``: the command line of the tool, the top floor of the house.

It alone knows argparse and flag names: every subcommand (one module in
:mod:`brainmech.commands`) parses its options, checks that its outputs can be written, and
calls library code, which raises errors in domain terms.  See docs/architecture.md.
"""
