"""What a sketch's timing costs in accuracy: the same white-noise excitation of the same
plant, sampled as sketches of each kind take their samples, read as the driver reads
ASCII lines (sample k at k T), through the project's own ETFE.

Regimes and the measurement: ``labbench.sim_backend.sketch_timing`` (``etfe_errors``): a print scheduled on micros() (with a
micros or no time field: the driver places both on the grid alike), on millis() (a
millis field: timer0's 1.024 ms steps, invisible in the stamps), and a ``delay()`` loop
without a time field (its period is the delay plus 0.2 ms of work, which the host cannot
see). The host answers each sample, so the force is held over the board's own
intervals. Error: |Z - Z_sampled| / |Z_sampled| over 2-100 rad/s, Z_sampled the exact
sampled model of the rig's nominal plant at T; the encoder's counts in all of them.
The delay loop's error is predicted exactly by reading the sampled model at the
board's longer period as if it were T (``predicted``).

Run: ``.venv/bin/python bench/bench_stamps.py [SECONDS]`` (default 120 s records).
"""
from __future__ import annotations

import sys

from labbench.sim_backend.sketch_timing import BAND, WORK_S, etfe_errors

def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 120.0
    print(f"ETFE error over {BAND[0]:g}-{BAND[1]:g} rad/s against the exact sampled model, "
          f"{seconds:g} s records (median / max relative)")
    for T in (0.01, 0.002):
        for name, row in etfe_errors(T, seconds).items():
            extra = (f"; predicted by the {100 * WORK_S / T:.0f} % longer period "
                     f"{100 * row['predicted_median']:.2f} %, measured within "
                     f"{100 * row['vs_predicted']:.2f} % of it" if "vs_predicted" in row else "")
            print(f"  T = {T * 1e3:g} ms  {name:<20} {100 * row['median']:6.2f} % / "
                  f"{100 * row['max']:6.2f} %{extra}")


if __name__ == "__main__":
    main()
