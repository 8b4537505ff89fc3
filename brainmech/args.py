"""Argument types of the command line: numbers are validated where they enter.

Each type raises ``argparse.ArgumentTypeError`` (exit code 2, one line naming the option)
for text that is not what the option needs: not a number, NaN or infinite, a list that is
not comma-separated numbers.  Whether a number makes physical sense (nu0 < 0.5, alpha != 0)
is the library's to say, in domain terms.
"""

from __future__ import annotations

import argparse
import math
import re


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def finite(text: str) -> float:
    return _number(text)


def positive(text: str) -> float:
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def non_negative(text: str) -> float:
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def count(minimum: int = 1):
    """A whole number >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, "
                                             f"got {text!r}")
        return v

    parse.__name__ = f"count>={minimum}"
    return parse


def floats(text: str) -> tuple[float, ...]:
    """Comma-separated finite numbers."""
    parts = [t for t in text.split(",") if t.strip()]
    vals = []
    for t in parts:
        try:
            v = float(t)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected comma-separated numbers, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
        vals.append(v)
    if not vals:
        raise argparse.ArgumentTypeError("expected at least one number")
    return tuple(vals)


def interval(text: str) -> tuple[float, float]:
    """Two numbers ``lo,hi`` with lo < hi."""
    vals = floats(text)
    if len(vals) != 2 or not vals[0] < vals[1]:
        raise argparse.ArgumentTypeError(f"expected two numbers lo,hi with lo < hi, got {text!r}")
    return vals


def names(text: str) -> list[str]:
    """A comma list of names (empty entries dropped)."""
    out = [t.strip() for t in text.split(",") if t.strip()]
    if not out:
        raise argparse.ArgumentTypeError("expected at least one name")
    return out


def accept_negative_lists(p: argparse.ArgumentParser) -> None:
    """Let negative comma lists through as option values (``--alpha -25,5``,
    ``--alpha-range -40,-2``); argparse otherwise only recognises single negative numbers
    and takes ``-25,5`` for an option."""
    p._negative_number_matcher = re.compile(r"^-\.?\d[\d.,eE+-]*$")


def channel_noise(text: str) -> dict[str, float]:
    """``stress=0.01,torque=0.02,axial_force=0.5``: a stated noise SD per channel, in the
    channel's unit (kPa, mN mm, mN)."""
    from brain_fe.vocabulary import CHANNELS

    out = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in CHANNELS:
            raise argparse.ArgumentTypeError(
                f"expected CHANNEL=SD with CHANNEL one of {', '.join(CHANNELS)}, got {item!r}")
        v = positive(value)
        out[name] = v
    if not out:
        raise argparse.ArgumentTypeError("expected at least one CHANNEL=SD")
    return out


def noise_option(text: str) -> dict:
    """``--noise``: ``CH=SD,...`` for every specimen (see :func:`channel_noise`), or a
    JSON file ``{specimen: {CH: SD}}`` such as the ``noise.json`` that ``brainmech
    import`` writes (each specimen its own measured noise; the specimen ``"*"``: every
    specimen not listed).  In the file a channel's value may also state its whole noise,
    ``{"white": SD, "correlated": SD, "correlation_time_s": s, "drift_per_s": rate,
    "more_correlated": [[SD, s], ...]}`` (:func:`diagnosis.noise.statement`), and then
    nothing of it is fitted."""
    import json
    from pathlib import Path

    from brain_fe.vocabulary import CHANNELS
    from diagnosis.noise import statement

    if "=" in text:
        return channel_noise(text)
    path = Path(text)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise argparse.ArgumentTypeError(
            f"{text}: no such file (expected CH=SD,... or a noise.json)") from None
    except (OSError, ValueError) as exc:
        raise argparse.ArgumentTypeError(f"{text}: not a JSON file ({exc})") from None
    if not isinstance(data, dict) or not data:
        raise argparse.ArgumentTypeError(f"{text}: expected {{specimen: {{channel: SD}}}}")
    out = {}
    for spec, chans in data.items():
        if not isinstance(chans, dict):
            raise argparse.ArgumentTypeError(
                f"{text}: specimen {spec!r}: expected {{channel: SD}}, got {chans!r}")
        out[str(spec)] = {}
        for ch, sd in chans.items():
            if ch not in CHANNELS:
                raise argparse.ArgumentTypeError(
                    f"{text}: specimen {spec!r}: unknown channel {ch!r} (expected one of "
                    f"{', '.join(CHANNELS)})")
            try:
                out[str(spec)][ch] = statement(sd)
            except ValueError as exc:
                raise argparse.ArgumentTypeError(
                    f"{text}: specimen {spec!r}, channel {ch!r}: {exc}") from None
    return {"by_specimen": out}
