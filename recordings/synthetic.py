"""Synthetic recordings made by the project's own FE model, with known parameters.

Noise model: additive Gaussian noise on every recorded channel with a standard deviation
of ``noise`` times the channel's peak absolute value over the series (``noise = 0.01`` is
the "1 % noise" of the verification). The tables follow DESIGN.md section 6.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from mpi4py import MPI

from brain_fe import geometry
from brain_fe.materials import MaterialParameters
from brain_fe.model import ForwardModel
from brain_fe.protocols import make
from brain_fe.vocabulary import (
    AXIAL_FORCE,
    CHANNELS,
    COMPRESSION_TENSION,
    TEST_CHANNELS,
    TORSION,
)

from .schema import RECORDING_COLUMNS

DEFAULT_TESTS = ((COMPRESSION_TENSION, 0.15), (TORSION, 0.15), (TORSION, 0.30))


def record(fm: ForwardModel, params, protocols, specimen: str, *, noise: float, rng,
           artefacts=None, interface=None, amplitudes=None) -> pd.DataFrame:
    """Recordings of one specimen: ``fm`` run through every protocol, Gaussian noise of
    ``noise`` times each channel's peak added, in the recordings-table layout.
    ``amplitudes`` (default: each protocol's own) label the tests in the table."""
    if amplitudes is None:
        amplitudes = [prot.amplitude for prot in protocols]
    rows = []
    for prot, amp in zip(protocols, amplitudes, strict=True):
        df = fm.run(prot, params, artefacts=artefacts, interface=interface)
        for ch in (CHANNELS[c].column for c in TEST_CHANNELS[prot.test]):
            peak = float(np.max(np.abs(df[ch])))
            df[ch] = df[ch] + noise * peak * rng.normal(size=len(df))
        df.insert(0, "specimen", specimen)
        df.insert(1, "test", prot.test)
        df.insert(2, "amplitude", amp)
        rows.append(df)
    return recordings_table(rows)


def recordings_table(parts: Sequence[pd.DataFrame]) -> pd.DataFrame:
    """The model's outputs of several tests (each with ``specimen``, ``test``,
    ``amplitude``) as one recordings table: every column of the layout, in its order."""
    out = pd.concat(parts, ignore_index=True)
    for c in RECORDING_COLUMNS:
        if c not in out:
            out[c] = np.nan
    # recorded in torsion only; compression/tension reports the stress
    out.loc[out.test == COMPRESSION_TENSION, AXIAL_FORCE] = np.nan
    return out[list(RECORDING_COLUMNS)]


def make_recordings(specimens: pd.DataFrame, truth: pd.DataFrame, *, noise: float = 0.01,
                    seed: int = 0, nu0: float = 0.49, refinement: int | None = None,
                    tests: Sequence[tuple[str, float]] = DEFAULT_TESTS,
                    model_cache: dict | None = None) -> pd.DataFrame:
    """Recordings (one row per point) of every specimen in ``specimens`` (columns of the
    specimens table) with the parameters of ``truth`` (columns specimen, mu_kPa, alpha)."""
    rng = np.random.default_rng(seed)
    cache = {} if model_cache is None else model_cache
    parts = []
    truth = truth.set_index("specimen")
    for s in specimens.itertuples(index=False):
        R, H = float(s.radius_mm), float(s.height_mm)
        if (R, H) not in cache:
            cache[(R, H)] = ForwardModel(geometry.make("axisymmetric", R, H, refinement,
                                                       comm=MPI.COMM_SELF))
        t = truth.loc[s.specimen]
        p = MaterialParameters(mu=(float(t.mu_kPa),), alpha=(float(t.alpha),), nu0=nu0)
        parts.append(record(cache[(R, H)], p, [make(test, amp) for test, amp in tests],
                            s.specimen, noise=noise, rng=rng,
                            amplitudes=[amp for _, amp in tests]))
    return pd.concat(parts, ignore_index=True)
