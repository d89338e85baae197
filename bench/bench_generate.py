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
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--resolution", default="512x256")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="iae_bench_"))
    results = []
    try:
        for w in args.workers:
            out = tmp / f"w{w}"
            # warm-up run of a few samples builds nothing persistent; each run starts cold,
            # so the figure includes Blender start-up, sky generation and car building.
            r = run("intrinsics", out, args.count, w, ["--resolution", args.resolution])
            sps = args.count / r["wall_s"]
            results.append({"workers": w, "samples": args.count, **r, "samples_per_s": sps})
            print(f"intrinsics {args.resolution} workers={w}: {args.count} samples in {r['wall_s']:.1f} s "
                  f"= {sps:.2f} samples/s (end to end, cold start); peak RSS of one process "
                  f"{r['peak_rss_mib_max_process']:.0f} MiB", flush=True)
            shutil.rmtree(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps({"machine": {"cpus": os.cpu_count()}, "results": results}, indent=2))


if __name__ == "__main__":
    main()
