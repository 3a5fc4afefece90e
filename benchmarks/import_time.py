"""How long ``import magcal`` takes against its floor, ``import numpy, scipy.linalg`` (issue 27).

Each import runs in a fresh interpreter (``python -X importtime``), alternating the two, and the table gives the
median of the cumulative time ``-X importtime`` reports for the top-level imports, in ms. Also timed: the modules
the first calibration loads (``magcal.calibrate``), and the command line's start (``magcal --help``).

Run: ``python benchmarks/import_time.py [--repeats 15]``
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time


def cumulative_ms(statement: str, modules: tuple[str, ...]) -> float:
    """Sum of ``-X importtime``'s cumulative microseconds for the top-level ``modules``, in ms."""
    err = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", statement], capture_output=True, text=True, check=True
    ).stderr
    total = 0
    for line in err.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        _, cumulative, name = (part.strip() for part in line.split("|"))
        if name in modules and cumulative.isdigit():
            total += int(cumulative)
    return total / 1000.0


def wall_ms(statement: str) -> float:
    code = f"import time; t = time.perf_counter(); {statement}; print((time.perf_counter() - t) * 1000)"
    return float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    cases = {
        "import numpy, scipy.linalg (the floor)": ("import numpy, scipy.linalg", ("numpy", "scipy.linalg")),
        "import magcal": ("import magcal", ("magcal",)),
    }
    times = {name: [] for name in cases}
    for _ in range(args.repeats):
        for name, (statement, modules) in cases.items():
            times[name].append(cumulative_ms(statement, modules))
    floor = statistics.median(times["import numpy, scipy.linalg (the floor)"])
    print(f"{'what':44s} {'median ms':>10s} {'x floor':>8s}   (-X importtime, cumulative, {args.repeats} runs)")
    for name, values in times.items():
        m = statistics.median(values)
        print(f"{name:44s} {m:10.1f} {m / floor:8.2f}")
    later = {
        "magcal.calibrate (first use: the engine)": "import magcal; magcal.calibrate",
        "magcal.diagnose + Diagnosis": "import magcal; magcal.diagnose; magcal.Diagnosis",
        "magcal.cli (the command line's parser)": "import magcal.cli",
    }
    print(f"\n{'wall time from a fresh interpreter':44s} {'median ms':>10s}")
    for name, statement in later.items():
        print(f"{name:44s} {statistics.median(wall_ms(statement) for _ in range(max(3, args.repeats // 3))):10.1f}")
    # the whole command, process start included, against the same interpreter importing magcal (issue 43: at most
    # 1.3x), alternating
    runs = {"python -c 'import magcal'": [sys.executable, "-c", "import magcal"]}
    runs["magcal --help"] = [sys.executable, "-c", "import sys; from magcal.cli import main; main(['--help'])"]
    whole = {name: [] for name in runs}
    for _ in range(args.repeats):
        for name, command in runs.items():
            t = time.perf_counter()
            subprocess.run(command, capture_output=True, check=False)
            whole[name].append((time.perf_counter() - t) * 1000)
    base = statistics.median(whole["python -c 'import magcal'"])
    print(f"\n{'a whole process':44s} {'median ms':>10s} {'x import':>8s}")
    for name, values in whole.items():
        print(f"{name:44s} {statistics.median(values):10.1f} {statistics.median(values) / base:8.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
