"""Generation benchmark: sustained samples/s at 512x256 and peak memory per worker, beside the bare
Cycles render rate of the same scenes with the same number of processes (render only: no passes
read back, no EXR, no hashing), and their ratio as the last line (`end-to-end / bare: 0.NN`).

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


BARE = """
import os, sys, time
w, h, start, count, threads = (int(v) for v in sys.argv[1:6])
if sys.argv[6]:  # pinned as iae-gen pins its workers
    os.sched_setaffinity(0, [int(c) for c in sys.argv[6].split(",")])
import bpy
from blender_gen.recipe import Recipe
from blender_gen.render import SampleRenderer
r = SampleRenderer(Recipe(kind="intrinsics", seed=0, width=w, height=h, background="environment"), threads=threads)
for i in range(start, start + 4):  # warm: the cars and skies of the timed samples' blocks are built
    r.set_up(i); bpy.ops.render.render(write_still=False)
spent = 0.0
for i in range(start + 4, start + 4 + count):
    r.set_up(i)
    t0 = time.perf_counter(); bpy.ops.render.render(write_still=False); spent += time.perf_counter() - t0
print(count / spent)
"""


def bare_rate(resolution: str, count: int, workers: int) -> float:
    """Cycles' own render rate: `workers` processes render disjoint samples side by side, each timing
    only bpy.ops.render.render and pinned to the CPUs `iae-gen` gives its workers; their rates add up."""
    from blender_gen.generate import cpu_groups, worker_threads

    w, h = resolution.split("x")
    threads = worker_threads(workers)
    groups = cpu_groups(workers)
    pins = [",".join(map(str, groups[k])) if groups else "" for k in range(workers)]
    per = max(1, count // workers)
    procs = [subprocess.Popen([sys.executable, "-c", BARE, w, h, str(k * (per + 4)), str(per), str(threads), pins[k]],
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
             for k in range(workers)]
    return sum(float(p.communicate()[0].strip().splitlines()[-1]) for p in procs)


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
            bare = bare_rate(args.resolution, args.count, w)
            results.append({"workers": w, "sustained_samples_per_s": sustained, "end_to_end_samples_per_s": end_to_end,
                            "startup_s": startup, "peak_rss_mib_one_process": long["peak_rss_mib_max_process"],
                            "bare_render_samples_per_s": bare})
            print(f"intrinsics {args.resolution} workers={w}: sustained {sustained:.2f} samples/s over {args.count} "
                  f"samples; end to end {end_to_end:.2f} samples/s for {args.warm + args.count} (start-up about "
                  f"{startup:.1f} s); peak RSS of one process {long['peak_rss_mib_max_process']:.0f} MiB", flush=True)
            shutil.rmtree(tmp / f"s{w}")
            shutil.rmtree(tmp / f"l{w}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps({"machine": {"cpus": os.cpu_count()}, "results": results}, indent=2))
    for r in results:
        print(f"workers={r['workers']}: sustained {r['sustained_samples_per_s']:.2f}, bare Cycles "
              f"{r['bare_render_samples_per_s']:.2f} samples/s")
    last = results[-1]
    print(f"end-to-end / bare: {last['sustained_samples_per_s'] / last['bare_render_samples_per_s']:.2f}")


if __name__ == "__main__":
    main()
