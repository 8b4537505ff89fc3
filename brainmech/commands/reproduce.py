"""``brainmech reproduce``: the whole study on the embedded synthetic brain bank."""

from __future__ import annotations

from ..errors import say


def add(sub) -> None:
    p = sub.add_parser(
        "reproduce", help="the whole study on the embedded synthetic brain bank",
        description="sample -> train -> identify (both fit sets) -> correlate -> report, on "
        "data/brain_bank. A re-run reuses finished stages. Writes OUT/report.md and "
        "OUT/summary.json.")
    p.add_argument("--profile", choices=["quick", "default", "paper"], default="quick")
    p.add_argument("--out", default="results/reproduce", metavar="DIR")
    p.set_defaults(run=run)


def run(args) -> int:
    from analysis.reproduce import reproduce, summary_lines
    from brain_fe.io import check_output_dir

    check_output_dir(args.out)
    say(summary_lines(reproduce(args.out, args.profile), args.out))
    return 0
