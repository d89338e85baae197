"""The intrinsics' render paths side by side: samples/s of the environment background looked up in
NumPy (the default), the same from Cycles' Environment pass (sets made before the lookup), the
black background, and the default without the extra layers (depth, part, gloss: sets made before
them), rendered in turns in one process so that every path sees the same machine.

Prints measured figures; nothing is asserted. Usage: python bench/bench_background.py
[--count 24] [--rounds 2] [--resolution 512x256] [--threads 1] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PATHS = {"environment, lookup": ("environment", "lookup", True), "environment, Cycles pass": ("environment", "cycles", True),
         "black": ("black", "lookup", True), "environment, lookup, 5 layers": ("environment", "lookup", False)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=24, help="timed samples per path and round (after 4 warm-up samples)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--resolution", default="512x256")
    ap.add_argument("--threads", type=int, default=1, help="Cycles threads")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    from blender_gen.recipe import Recipe
    from blender_gen.render import SampleRenderer

    w, h = (int(v) for v in a.resolution.split("x"))
    rates: dict[str, list[float]] = {k: [] for k in PATHS}
    for _ in range(a.rounds):
        for name, (background, method, extra) in PATHS.items():
            r = SampleRenderer(Recipe(kind="intrinsics", seed=4, width=w, height=h, background=background,
                                      environment_pass=method, **({} if extra else {"extra_layers": ()})),
                               threads=a.threads)
            with tempfile.TemporaryDirectory() as tmp:
                (Path(tmp) / "samples").mkdir()
                for i in range(4):  # builds the cars and loads the skies
                    r.render(i, Path(tmp))
                t0 = time.perf_counter()
                for i in range(4, 4 + a.count):
                    r.render(i, Path(tmp))  # render, read back, EXR written and hashed
                rates[name].append(a.count / (time.perf_counter() - t0))
            r.close()
    for name, v in rates.items():
        print(f"{name:26s} {statistics.median(v):6.2f} samples/s (rounds: {', '.join(f'{x:.2f}' for x in v)})")
    look, black = statistics.median(rates["environment, lookup"]), statistics.median(rates["black"])
    print(f"lookup / Cycles pass: {look / statistics.median(rates['environment, Cycles pass']):.2f}; "
          f"lookup / black: {look / black:.2f}; "
          f"8 layers / 5 layers: {look / statistics.median(rates['environment, lookup, 5 layers']):.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps({"resolution": a.resolution, "threads": a.threads, "count": a.count,
                                            "samples_per_s": rates}, indent=1) + "\n")


if __name__ == "__main__":
    main()
