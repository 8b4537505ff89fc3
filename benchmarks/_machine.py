"""What the benchmarks report about the machine they ran on, and how a benchmark script
reads its inputs and ends on bad ones."""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

from brainmech.errors import abort_other_ranks, one_line


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


def read_json(path, *needs: str):
    """A JSON input file; a malformed one, or one without a top-level field in ``needs``,
    is a ValueError naming the file (and the line and column)."""
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: line {exc.lineno} column {exc.colno}: {exc.msg}") \
            from None
    missing = [k for k in needs if not isinstance(data, dict) or k not in data]
    if missing:
        raise ValueError(f"{path}: no field {missing[0]!r}")
    return data


def run_script(main) -> None:
    """Run a script's ``main()`` and exit with its code.  Bad input (a missing or
    unreadable file, malformed JSON, a value out of range, a field an input lacks) ends
    the script with one line on stderr and exit status 1, without a traceback; under
    ``mpirun``, a file error of one rank ends the others too (they would wait for it)."""
    name = Path(sys.argv[0]).name
    try:
        code = main()
    except (OSError, ValueError, KeyError) as exc:
        msg = f"a field is missing: {exc}" if isinstance(exc, KeyError) else one_line(exc)
        sys.stderr.write(f"{name}: error: {msg}\n")
        if isinstance(exc, OSError):
            abort_other_ranks(1)
        code = 1
    except KeyboardInterrupt:
        sys.stderr.write(f"{name}: interrupted\n")
        code = 130
    sys.exit(code or 0)
