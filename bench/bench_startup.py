"""Start-up time of the command line: ``labbench --version`` and ``labbench --help``.

Goal (issue 24): each within 0.3 s. Measured as the best of --repeat runs of a fresh
interpreter (``python -m labbench ...``), beside the floor of the same interpreter
doing nothing (``python -c pass``) measured in the same run, so a loaded machine shows
as a higher floor rather than a false result.

    .venv/bin/python bench/bench_startup.py [--repeat 5]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

GOAL_S = 0.3


def best_of(argv: list[str], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, *argv], check=True, capture_output=True)
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    floor = best_of(["-c", "pass"], args.repeat)
    print(f"floor (python -c pass): {floor:.3f} s")
    ok = True
    for what in ("--version", "--help"):
        t = best_of(["-m", "labbench", what], args.repeat)
        met = t <= GOAL_S
        ok &= met
        print(f"labbench {what}: {t:.3f} s ({t / floor:.1f}x the floor; goal <= {GOAL_S} s: "
              f"{'met' if met else 'NOT met'})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
