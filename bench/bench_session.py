"""Cost of recording: the session writer and reader against plain file I/O.

A 2-minute 1 kHz run is 1200 pages of 100 samples x 8 channels. The writer runs
on the loop thread, so what matters is its cost per page against the 100 ms a
page takes to acquire, and against the floor: one plain ``os.write`` of the same
array bytes (measured in the same run). Reading back is compared with
``np.fromfile`` of the same bytes.

    .venv/bin/python bench/bench_session.py [--repeat 5]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from labbench import records
from labbench.sessions.session_format import SessionWriter, read_session

N_PAGES, PAGE = 1200, 100
T = 0.001


def stream(rng) -> list[dict]:
    out = [records.start_record({"name": "bench"}, {"name": "bench"}, 0),
           records.descriptor_record(T)]
    for i in range(N_PAGES):
        data = {name: rng.standard_normal(PAGE) for name in records.CHANNELS}
        data["seq"] = np.arange(i * PAGE, (i + 1) * PAGE)
        data["flags"] = np.zeros(PAGE, dtype=np.int64)
        out.append(records.page_record(i, data))
    out.append(records.stop_record("success"))
    return out


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    recs = stream(np.random.default_rng(0))
    blobs = [b"".join(np.asarray(v).tobytes() for v in r["data"].values())
             for r in recs if r["kind"] == records.PAGE]
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        counter = iter(range(10**6))

        def write_session():
            with SessionWriter(d, name=f"s{next(counter)}") as w:
                for r in recs:
                    w(r)
            write_session.path = w.path

        def write_plain():
            fd = os.open(d / f"raw{next(counter)}", os.O_WRONLY | os.O_CREAT)
            for b in blobs:
                os.write(fd, b)
            os.fsync(fd)
            os.close(fd)

        t_sess = best(write_session, args.repeat)
        t_raw = best(write_plain, args.repeat)
        raw_path = d / "raw.bin"
        raw_path.write_bytes(b"".join(blobs))
        t_read = best(lambda: sum(1 for _ in read_session(write_session.path)), args.repeat)
        t_read_raw = best(lambda: np.fromfile(raw_path, dtype=np.float64), args.repeat)
        size = write_session.path.stat().st_size
    per_page_us = t_sess / N_PAGES * 1e6
    print(f"session of {N_PAGES * PAGE} samples ({size / 1e6:.1f} MB, "
          f"{size / sum(map(len, blobs)) - 1:+.1%} over the raw arrays)")
    print(f"write: {per_page_us:.0f} us per page = {per_page_us / (PAGE * T * 1e6):.3%} of the "
          f"page's acquisition time; {t_sess / t_raw:.1f}x plain os.write + fsync")
    print(f"read:  {t_read * 1e3:.0f} ms for the whole run = {t_read / t_read_raw:.1f}x np.fromfile")


if __name__ == "__main__":
    main()
