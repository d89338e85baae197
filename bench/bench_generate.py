"""Generation benchmark: sustained samples/s at 512x256 and peak memory per worker.

Prints measured figures; nothing is asserted. Usage: python bench/bench_generate.py
[--count 200] [--workers 1 2]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(kind: str, out: Path, count: int, workers: int, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "blender_gen.cli", kind, "--out", str(out), "--count", str(count),
           "--workers", str(workers), "--quiet", *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(proc.stderr)
    # ru_maxrss of waited-for children: the largest single process (KiB on Linux)
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"wall_s": wall, "line": proc.stdout.strip(), "peak_rss_mib_max_process": peak_kib / 1024}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--count", type=int, default=200, help="samples in the sustained window")
    ap.add_argument("--warm", type=int, default=40, help="samples of the short run subtracted out")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--resolution", default="512x256")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="iae_bench_"))
    results = []
    try:
        for w in args.workers:
            # Two fresh runs, `warm` and `warm + count` samples: both pay Blender start-up, sky
            # generation and car building, so their difference is the sustained rate.
            short = run("intrinsics", tmp / f"s{w}", args.warm, w, ["--resolution", args.resolution])
            long = run("intrinsics", tmp / f"l{w}", args.warm + args.count, w, ["--resolution", args.resolution])
            sustained = args.count / (long["wall_s"] - short["wall_s"])
            end_to_end = (args.warm + args.count) / long["wall_s"]
            startup = short["wall_s"] - args.warm / sustained
            results.append({"workers": w, "sustained_samples_per_s": sustained, "end_to_end_samples_per_s": end_to_end,
                            "startup_s": startup, "peak_rss_mib_one_process": long["peak_rss_mib_max_process"]})
            print(f"intrinsics {args.resolution} workers={w}: sustained {sustained:.2f} samples/s over {args.count} "
                  f"samples; end to end {end_to_end:.2f} samples/s for {args.warm + args.count} (start-up about "
                  f"{startup:.1f} s); peak RSS of one process {long['peak_rss_mib_max_process']:.0f} MiB", flush=True)
            shutil.rmtree(tmp / f"s{w}")
            shutil.rmtree(tmp / f"l{w}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps({"machine": {"cpus": os.cpu_count()}, "results": results}, indent=2))


if __name__ == "__main__":
    main()
