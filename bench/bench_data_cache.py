"""What the training-size cache saves (`data.cache_gb`): loader cost per batch and training steps/s.

1. loader: CPU seconds per batch of the decoding dataset (EXR decode, sRGB encode, resize) and
   of the cache (a memory-mapped read), measured with process time in this process (workers=0),
   so a busy machine changes the figures little.
2. fit: steps/s of `iae-train fit` (cpu-small, 64x128, batch 4) with the cache off (two loader
   processes, as before) and on, each for --steps steps after the cache is built.

  python bench/bench_data_cache.py [--intrinsics DIR --real DIR] [--steps 60]
Without data it renders a small set first (intrinsics and PBR at 256x128) into --work.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def loader_cost(root: Path, stack: bool, h: int, w: int, batches: int, batch: int) -> tuple[float, float]:
    from train.data import CachedTensors, IntrinsicsData, RealImages

    ds = IntrinsicsData(root, h, w) if stack else RealImages(root, h, w)
    with tempfile.TemporaryDirectory() as tmp:
        cache = CachedTensors(ds, Path(tmp) / "c.npy", stack=stack)
        out = []
        for source in (ds, cache):
            t = time.process_time()
            for b in range(batches):
                for j in range(batch):
                    source[((b * batch + j) % len(ds), j % 2 == 1)]
            out.append((time.process_time() - t) / batches)
    return out[0], out[1]


def fit_rate(intr: Path, real: Path, steps: int, cache_gb: float, workers: int, work: Path) -> float:
    run = work / f"run_cache{cache_gb:g}"
    cmd = [sys.executable, "-m", "train.cli", "fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real",
           str(real), "--run-dir", str(run), "--max-steps", str(steps), "--quiet", "--set", f"data.cache_gb={cache_gb}",
           "--set", f"data.workers={workers}", "--set", "run.grid_every=100000", "--set", "run.checkpoint_every=100000"]
    subprocess.run(["rm", "-rf", str(run)])
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if out.returncode:
        raise SystemExit(out.stderr)
    # "RUN: step N (N steps in S s, R it/s)"; the cache is built before the step clock starts
    return float(out.stdout.strip().rsplit(",", 1)[1].split()[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--intrinsics", type=Path, default=None)
    ap.add_argument("--real", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "bench_data_cache")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--batches", type=int, default=50)
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    intr, real = a.intrinsics, a.real
    if intr is None or real is None:
        intr, real = a.work / "intrinsics", a.work / "real"
        gen = [sys.executable, "-m", "blender_gen.cli"]
        subprocess.run([*gen, "intrinsics", "--out", str(intr), "--count", "200", "--resolution", "256x128",
                        "--workers", "2", "--quiet"], check=True, cwd=ROOT)
        subprocess.run([*gen, "pbr", "--out", str(real), "--count", "40", "--resolution", "256x128", "--samples", "4",
                        "--workers", "2", "--quiet"], check=True, cwd=ROOT)
    rows = {}
    for name, root, stack in (("intrinsics", intr, True), ("real", real, False)):
        dec, cached = loader_cost(root, stack, 64, 128, a.batches, 4)
        rows[name] = {"decode_ms_per_batch": dec * 1e3, "cache_ms_per_batch": cached * 1e3}
        print(f"loader {name:<10} CPU per batch of 4 at 64x128: decode {dec * 1e3:7.1f} ms, cache {cached * 1e3:6.2f} ms")
    off = fit_rate(intr, real, a.steps, 0, 2, a.work)
    on = fit_rate(intr, real, a.steps, 4.0, 0, a.work)
    rows["fit"] = {"steps": a.steps, "cache_off_workers2_it_s": off, "cache_on_it_s": on}
    print(f"fit cpu-small 64x128 batch 4, {a.steps} steps: cache off (2 loader processes) {off:.2f} it/s, "
          f"cache on {on:.2f} it/s ({on / off:.2f}x)")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
