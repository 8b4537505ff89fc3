"""What the benchmarks report about the machine they ran on."""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else ``platform.processor()``."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def micro_arguments() -> argparse.Namespace:
    """``--repeats`` (blocks of calls; the median is stated) and ``--out`` (the results
    directory, ``benchmarks/results`` by default, made if missing) of a micro-benchmark."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    return a


def write_result(out_dir: str, name: str, fields: dict) -> str:
    """``fields`` with the machine first, as ``out_dir/name``; says where."""
    path = os.path.join(out_dir, name)
    with open(path, "w") as fh:
        json.dump({"machine": {"cpu": cpu_model(), "python": platform.python_version()},
                   **fields}, fh, indent=1)
    print("wrote", path)
    return path


def median_per_call(call, n: int, repeats: int) -> float:
    """Median over ``repeats`` blocks of the time of one ``call()`` [s], each block
    ``n`` calls in a row."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            call()
        times.append((time.perf_counter() - t0) / n)
    return statistics.median(times)
