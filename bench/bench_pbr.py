"""PBR benchmark: seconds per 512x256 frame and the error it reaches.

For each sample count, renders the same views and compares the (denoised) image with a
high-sample render of the same view: RMS error in sRGB [0, 1] over the frame. Prints
measured figures; nothing is asserted. Usage: python bench/bench_pbr.py [--views 4]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from blender_gen.conversions import linear_to_srgb
from blender_gen.recipe import Recipe
from blender_gen.generate import make_renderer


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--samples", type=int, nargs="+", default=[8, 12, 16, 32])
    ap.add_argument("--reference", type=int, default=256)
    ap.add_argument("--resolution", default="512x256")
    ap.add_argument("--noise-threshold", type=float, nargs="+", default=[Recipe.noise_threshold],
                    help="adaptive sampling thresholds of the timed renders (the reference keeps the default)")
    ap.add_argument("--denoise", nargs="+", default=["FAST:FAST"], metavar="QUALITY:PREFILTER",
                    help="OIDN quality (FAST, BALANCED, HIGH) and prefilter (FAST, ACCURATE) of the timed renders; "
                         "the generator's is FAST:FAST, which the reference keeps")
    ap.add_argument("--pattern", nargs="+", default=[None], metavar="PATTERN",
                    help="Cycles sampling pattern of the timed renders (AUTOMATIC, TABULATED_SOBOL, BLUE_NOISE); "
                         "default: the generator's, which the reference keeps")
    args = ap.parse_args()
    denoise = []
    for d in args.denoise:
        q, _, pf = d.upper().partition(":")
        if q not in ("FAST", "BALANCED", "HIGH") or pf not in ("FAST", "ACCURATE", "NONE"):
            ap.error(f"--denoise {d!r}: expected QUALITY:PREFILTER, e.g. HIGH:ACCURATE")
        denoise.append((q, pf))
    w, h = (int(v) for v in args.resolution.split("x"))
    def renderer(spp: int, threshold: float = Recipe.noise_threshold, quality: str = "FAST", prefilter: str = "FAST",
                 pattern: str | None = None):
        # views_per_car = views: one car and environment, so every frame is a steady-state
        # frame. A fresh renderer per sample count: Cycles' persistent session keeps the
        # sample count of its first render.
        recipe = Recipe(kind="pbr", seed=5, width=w, height=h, cars=("procedural:heldout",), samples=spp,
                        views_per_car=args.views, noise_threshold=threshold)
        r = make_renderer(recipe, threads=0)
        r.scene.cycles.denoising_quality, r.scene.cycles.denoising_prefilter = quality, prefilter
        if pattern:
            r.scene.cycles.sampling_pattern = pattern
        r.render_layers(0)  # builds the car, the sky and the light-sampling map
        return r

    r = renderer(args.reference)
    ref = {}
    t0 = time.perf_counter()
    for i in range(args.views):
        ref[i] = linear_to_srgb(r.render_layers(i)[0]["rgb"])
    ref_s = (time.perf_counter() - t0) / args.views
    print(f"reference: {args.reference} samples/pixel, {ref_s:.1f} s/frame", flush=True)
    results = []
    runs = ((s, t, d, p) for s in args.samples for t in args.noise_threshold for d in denoise for p in args.pattern)
    for spp, threshold, (quality, prefilter), pattern in runs:
        r = renderer(spp, threshold, quality, prefilter, pattern)
        pattern = r.scene.cycles.sampling_pattern
        times, errs = [], []
        for i in range(args.views):
            t = time.perf_counter()
            img = r.render_layers(i)[0]["rgb"]
            times.append(time.perf_counter() - t)
            errs.append(float(np.sqrt(np.mean((linear_to_srgb(img) - ref[i]) ** 2))))
        results.append({"samples": spp, "noise_threshold": threshold, "denoise": f"{quality}:{prefilter}",
                        "pattern": pattern,
                        "s_per_frame": float(np.mean(times)),
                        "rms_srgb": float(np.mean(errs))})
        print(f"pbr {w}x{h} {spp:>3} samples/pixel (adaptive to {threshold:g}, OIDN {quality}:{prefilter}, {pattern}): "
              f"{np.mean(times):.2f} s/frame, RMS error vs {args.reference} spp {np.mean(errs):.4f} (sRGB 0..1)",
              flush=True)
    print(json.dumps({"reference_s_per_frame": ref_s, "results": results}, indent=2))


if __name__ == "__main__":
    main()
