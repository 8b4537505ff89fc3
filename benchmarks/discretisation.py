"""How far the diagnosis's working model is from a converged one, in noise SDs.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/discretisation.py [--specimens 6]
        [--seed 0] [--reference 4] [--substeps 4]

For open-world specimens (:func:`diagnosis.open_world.draw_specimen`: radius 3-5 mm,
height 3-7 mm, 1-3 cycles, drawn protocols and clock) and truths without an effect, with a
Maxwell branch and with Mullins softening, it compares on the recorded rows

* the working model: refinement 1 on the recorded path, plus the deferred correction from
  refinement 2 scaled to the Richardson limit (exactly as ``diagnosis.engine._base``), and
* the converged reference: refinement ``--reference`` with ``--substeps`` FE steps per
  recorded interval, interpolated at the recorded times (the open-world generator's path),

in units of the rig noise the open world draws for that specimen (``noise_sd``).  The
uncorrected gap (k = 1 alone) is printed beside it.  Writes
``benchmarks/results/discretisation.json`` and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from _machine import run_script

HERE = Path(__file__).resolve().parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--specimens", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reference", type=int, default=4)
    ap.add_argument("--substeps", type=int, default=4)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    from brain_fe.parameters import Param
    from diagnosis.engine import RICHARDSON_ORDER
    from diagnosis.open_world import (
        _shapes,
        draw_noise,
        draw_specimen,
        make_truth,
        noise_sd,
        record_times,
        simulate,
    )
    from recordings.observations import observations
    from simulators.fe import FESimulator

    rng = np.random.default_rng(a.seed)
    factor = 2**RICHARDSON_ORDER / (2**RICHARDSON_ORDER - 1)
    rows = []
    models: dict = {}
    for i in range(a.specimens):
        spec = draw_specimen(rng)
        mu = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        base = {Param("mu", 0): mu, Param("alpha", 0): float(rng.uniform(-25, -8))}
        shapes = _shapes(rng, mu, spec)
        times = [record_times(spec, p, rng) for p in spec.protocols()]
        for effects in ({}, {"viscoelastic": 3.0}, {"mullins": 2.0}):
            truth = make_truth(base, effects, shapes)
            ref = simulate(spec, truth, times, refinement=a.reference, substeps=a.substeps,
                           models=models)
            ref["specimen"] = "s"
            obs = observations(ref)
            sd = obs["channel"].map(noise_sd(draw_noise(ref, ("white",), rng, spec)))
            sd = sd.to_numpy(float)
            k1 = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=1)
            k2 = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=2)
            y1 = k1.predict(truth.values, []).y
            y2 = k2.predict(truth.values, []).y
            y = obs["value"].to_numpy(float)
            raw = np.abs(y1 - y) / sd
            corr = np.abs(y1 + factor * (y2 - y1) - y) / sd
            rows.append({"specimen": i, "effect": "+".join(effects) or "none",
                         "radius_mm": spec.radius_mm, "height_mm": spec.height_mm,
                         "tests": len(times), "cycles": spec.cycles,
                         "uncorrected_max": float(raw.max()),
                         "uncorrected_rms": float(np.sqrt(np.mean(raw**2))),
                         "corrected_max": float(corr.max()),
                         "corrected_rms": float(np.sqrt(np.mean(corr**2)))})
            print(rows[-1], flush=True)  # noqa: T201 - a benchmark script reports
    out = HERE / "results" / "discretisation.json"
    out.write_text(json.dumps({"args": vars(a), "rows": rows}, indent=1))
    print("| effect | cases | k=1 max / noise | k=1 RMS | corrected max | corrected RMS |")  # noqa: T201
    print("|---|---|---|---|---|---|")  # noqa: T201
    for eff in dict.fromkeys(r["effect"] for r in rows):
        g = [r for r in rows if r["effect"] == eff]
        print(f"| {eff} | {len(g)} | {max(r['uncorrected_max'] for r in g):.2f} | "  # noqa: T201
              f"{np.median([r['uncorrected_rms'] for r in g]):.2f} | "
              f"{max(r['corrected_max'] for r in g):.2f} | "
              f"{np.median([r['corrected_rms'] for r in g]):.2f} |")


if __name__ == "__main__":
    run_script(main)
