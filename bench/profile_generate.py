"""Where an intrinsics sample's time goes, one worker: cProfile of `SampleRenderer.render` over
--count samples after --warm ones (the cars and skies of the first block are built then), the
functions with the largest cumulative time first.

Prints measured figures; nothing is asserted. Usage: python bench/profile_generate.py
[--count 24] [--resolution 512x256] [--background environment|black] [--top 30]
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=24)
    ap.add_argument("--warm", type=int, default=4)
    ap.add_argument("--resolution", default="512x256", help="WIDTHxHEIGHT")
    ap.add_argument("--background", default="environment", choices=["environment", "black"])
    ap.add_argument("--top", type=int, default=30)
    a = ap.parse_args()
    w, h = (int(v) for v in a.resolution.split("x"))

    from blender_gen.recipe import Recipe
    from blender_gen.render import SampleRenderer

    r = SampleRenderer(Recipe(kind="intrinsics", seed=0, width=w, height=h, background=a.background), threads=1)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        (out / "samples").mkdir()
        for i in range(a.warm):
            r.render(i, out)
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        for i in range(a.warm, a.warm + a.count):
            r.render(i, out)
        prof.disable()
        spent = time.perf_counter() - t0
    print(f"{a.count} samples at {w}x{h}, one worker, one Cycles thread: {spent / a.count * 1000:.0f} ms per sample")
    pstats.Stats(prof).sort_stats("cumulative").print_stats(a.top)
    r.close()


if __name__ == "__main__":
    main()
