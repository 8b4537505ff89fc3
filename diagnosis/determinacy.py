"""Is a verdict determined by the recordings?  Diagnose again with their last digits changed.

A diagnosis is reproducible (the same recordings give bit-identical results, alone or in
a batch), but it is not continuous: its fits stop at a tolerance, its FE solves converge
to one, and some of its choices are between near-equal optima (the noise likelihood of a
single ramp can take a smooth misfit for a slow drift or not, within 0.01 of -2 log L).
A change of the recorded numbers in their last digits, far below any instrument's
resolution, can then move the verdict (docs/real-data.md: measured on the rheometer
exports).  Such a verdict is a matter of rounding, not of the data.

:func:`check` runs the diagnosis a second time on :func:`last_digits` of the observations
and, where the verdict or its status moves, says *cannot tell* (``brainmech diagnose
--check-digits``; twice the time).
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

log = logging.getLogger(__name__)

RELATIVE_SD = 4e-16  # about two units in the last place of a double (2**-52 = 2.2e-16)
PERTURBED = ("control", "value", "time_s")  # what the diagnosis reads of a recording
SEED = 1
NOT_DETERMINED = ("the verdict changes when the recorded numbers change in their last "
                  "digits ({} -> {}): it is a matter of rounding, not determined by these "
                  "recordings")


def last_digits(obs: pd.DataFrame, seed: int = SEED) -> pd.DataFrame:
    """A copy of ``obs`` with each recorded number multiplied by ``1 + RELATIVE_SD g``
    (g standard normal, seeded); the protocol columns are kept."""
    out = obs.copy()
    rng = np.random.default_rng(seed)
    for c in PERTURBED:
        if c in out:
            x = out[c].to_numpy(float)
            out[c] = x * (1.0 + RELATIVE_SD * rng.standard_normal(x.size))
    out.attrs = dict(obs.attrs)
    return out


def check(d, rediagnose) -> dict:
    """Compare ``d`` (a :class:`~diagnosis.engine.Diagnosis`) with ``rediagnose(obs)`` run on
    :func:`last_digits` of its observations; record the comparison in ``d.last_digits``
    and, where the verdict or status moves, add the *cannot tell*.  Returns the record."""
    other = rediagnose(last_digits(d.obs))
    same = (other.verdict, other.status) == (d.verdict, d.status)
    record = {"relative_sd": RELATIVE_SD, "seed": SEED, "verdict": other.verdict,
              "status": other.status, "same": bool(same)}
    d.last_digits = record
    if not same:
        why = NOT_DETERMINED.format(f"{d.verdict} ({d.status})",
                                    f"{other.verdict} ({other.status})")
        log.warning("%s", why)
        d.cannot_tell = f"{d.cannot_tell}; {why}" if d.cannot_tell else why
    return record
