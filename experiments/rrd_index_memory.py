"""Memory of rerun's file writer against the number of chunks it wrote (issue 12's remainder:
a run with the recording on grew with its length where the same run without it did not).

Each case is one fresh process that logs only to a rerun file recording (``RecordingStream.save``),
frame by frame, what ``RerunSink.log_frame`` logs for the free controller (a LineStrips3D, a
Points3D and two Transform3D entities, on the ``frame`` and ``sim_time`` timelines), tiny data, and
flushes the recording every ``--flush`` frames: every flush ends one chunk of every entity.  Per
case: anonymous RSS (/proc/self/smaps_rollup) after the first and after the last frame, before the
file is closed, and the process's peak RSS after it is closed (the writer builds the footer then),
with rerun's footer (the default, what the sink writes) and without (``write_footer=False``).

The writer keeps, per chunk, a row of its footer's manifest (chunk id, byte span, entity, and a
time range per timeline and component) until the footer is written; without the footer the
memory stays flat.  Prints a markdown table; writes nothing.
Usage:  python -m experiments.rrd_index_memory [--frames 2000 20000] [--flush 1]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys

from experiments.common import positive_int, writable_file


def anon_mb() -> float:
    with open("/proc/self/smaps_rollup") as f:
        for line in f:
            if line.startswith("Anonymous"):
                return int(line.split()[1]) / 1024
    return float("nan")


def worker(frames: int, flush: int, footer: bool, path: str) -> dict:
    import numpy as np
    import rerun as rr

    rec = rr.RecordingStream("rrd_index_memory", recording_id="probe")
    rec.save(path, write_footer=footer)
    x = np.zeros((4, 3), np.float32)
    first = None
    for f in range(frames):
        rec.set_time("frame", sequence=f)
        rec.set_time("sim_time", duration=f / 25.0)
        rec.log("/world/hair", rr.LineStrips3D([x[:2], x[2:]], radii=0.001, colors=[[200, 150, 90]]))
        rec.log("/world/roots", rr.Points3D(x[::2], radii=0.0015, colors=[[60, 60, 200]]))
        rec.log("/world/body", rr.Transform3D(translation=[f * 1e-3, 0, 0], quaternion=[0, 0, 0, 1]))
        rec.log("/world/colliders/c", rr.Transform3D(translation=[0, f * 1e-3, 0], quaternion=[0, 0, 0, 1]))
        if (f + 1) % flush == 0:
            rec.flush()
        if first is None and f + 1 >= flush:
            first = (f + 1, anon_mb())
    rec.flush()
    last = anon_mb()
    rec.disconnect()
    return {"frames": frames, "chunks": 4 * (frames // flush), "first_frames": first[0], "anon_first": first[1],
            "anon_last": last, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "file_mb": os.path.getsize(path) / 1e6}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=positive_int, nargs="+", default=[2000, 20000])
    ap.add_argument("--flush", type=positive_int, default=1, help="flush the recording every this many frames")
    ap.add_argument("--worker", nargs=3, metavar=("FRAMES", "FOOTER", "PATH"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        frames, footer, path = args.worker
        try:   # the parent's arguments (hidden): checked all the same, before the recording is made
            positive_int(frames), writable_file(path)
        except argparse.ArgumentTypeError as exc:
            ap.error(f"argument --worker: {exc}")
        print(json.dumps(worker(int(frames), args.flush, footer == "1", path)))
        return
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory(prefix="rrd_index_memory_") as tmp:
        for footer in (True, False):
            for n in args.frames:
                out = subprocess.run([sys.executable, "-m", "experiments.rrd_index_memory", "--flush", str(args.flush),
                                      "--worker", str(n), "1" if footer else "0", os.path.join(tmp, f"{n}.rrd")],
                                     check=True, capture_output=True, text=True).stdout
                r = json.loads(out.strip().splitlines()[-1])
                r["footer"] = footer
                rows.append(r)
                print(r, file=sys.stderr)
    print("| footer | frames | chunks | anon after first flush (MB) | anon at the end (MB) | "
          "growth per 1,000 chunks (MB) | peak RSS (MB) | file (MB) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        per = (r["anon_last"] - r["anon_first"]) / max(1, r["chunks"] - 4 * r["first_frames"] // args.flush) * 1000
        print(f"| {'yes' if r['footer'] else 'no'} | {r['frames']} | {r['chunks']} | {r['anon_first']:.1f} | "
              f"{r['anon_last']:.1f} | {per:.2f} | {r['peak']:.1f} | {r['file_mb']:.1f} |")


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
