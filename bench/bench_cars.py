"""Car model benchmark: build/import time per model; samples/s when models are reused for
several views, switched every view, rebuilt every view, or drawn anew per block (procedural:random). Prints measured figures.
Usage: python bench/bench_cars.py [--samples 60]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from blender_gen.recipe import Recipe
from blender_gen.render import SampleRenderer

ROOT = Path(__file__).resolve().parent.parent
KENNEY = ROOT.parent / "shared" / "assets" / "cars3d"
RULES = ROOT / "data_manifests" / "kenney_car_kit_rules.toml"


def throughput(views_per_car: int, n: int, rebuild: bool, w: int, h: int) -> float:
    r = SampleRenderer(Recipe(kind="intrinsics", seed=1, width=w, height=h, views_per_car=views_per_car), threads=0)
    for spec in r.car_specs:  # every model built once, every sky made once
        r.car(spec)
    for name in r.env_names:
        r.env_image(name)
    r.render_layers(0)
    t = time.perf_counter()
    for i in range(1, n + 1):
        if rebuild:
            r.forget_cars()
        r.render_layers(i)
    dt = time.perf_counter() - t
    r.close()
    return n / dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--resolution", default="512x256")
    args = ap.parse_args()
    w, h = (int(v) for v in args.resolution.split("x"))
    r = SampleRenderer(Recipe(kind="intrinsics", seed=0, width=w, height=h, cars=("procedural",)), threads=0)
    times = []
    for spec in r.car_specs:
        t = time.perf_counter()
        r.car(spec)
        times.append(time.perf_counter() - t)
    print(f"procedural catalogue: {len(times)} models, build (NumPy geometry + Blender objects) "
          f"mean {1000 * np.mean(times):.0f} ms, max {1000 * np.max(times):.0f} ms per model", flush=True)
    r.close()
    result = {"procedural_build_ms_mean": 1000 * float(np.mean(times)), "procedural_build_ms_max": 1000 * float(np.max(times))}
    if KENNEY.is_dir():
        files = tuple(str(p) for p in sorted(KENNEY.glob("*.glb")))
        r = SampleRenderer(Recipe(kind="intrinsics", seed=0, width=w, height=h, cars=files, car_rules=str(RULES)), 0)
        imp = []
        for spec in r.car_specs:
            t = time.perf_counter()
            r.car(spec)
            imp.append(time.perf_counter() - t)
        r.close()
        result["kenney_import_ms_mean"] = 1000 * float(np.mean(imp))
        print(f"Kenney glTF models: {len(imp)} files, import + part rules + objects mean {1000 * np.mean(imp):.0f} ms, "
              f"max {1000 * np.max(imp):.0f} ms per model", flush=True)
    for label, vpc, rebuild in (("reused for 8 views", 8, False), ("reused for 4 views (default)", 4, False),
                                ("switched every view (kept built)", 1, False), ("rebuilt every view", 1, True)):
        sps = throughput(vpc, args.samples, rebuild, w, h)
        result[label] = sps
        print(f"intrinsics {w}x{h}, one process, model {label}: {sps:.2f} samples/s", flush=True)
    # procedural:random: a new car per block of views, built (sampled, checked against the held-out
    # models, meshed) when its block starts; the renderer keeps the last few.
    r = SampleRenderer(Recipe(kind="intrinsics", seed=1, width=w, height=h, cars=("procedural:random",)), threads=0)
    r.render_layers(0)
    t = time.perf_counter()
    for i in range(1, args.samples + 1):
        r.render_layers(i)
    sps = args.samples / (time.perf_counter() - t)
    r.close()
    result["procedural:random, a new car every 4 views"] = sps
    print(f"intrinsics {w}x{h}, one process, procedural:random (a new car every 4 views): {sps:.2f} samples/s", flush=True)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
