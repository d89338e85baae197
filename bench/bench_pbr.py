"""PBR benchmark: seconds per 512x256 frame and the error it reaches.

For each sample count, renders the same views and compares the (denoised) image with a
high-sample render of the same view: RMS error in sRGB [0, 1] over the frame, and which share of
the squared error lies on the car, along its outline and on the background. Prints
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


REGIONS = ("car", "edges", "background")


def split_regions(car: np.ndarray) -> dict[str, np.ndarray]:
    """The car's inside, a 2-pixel band either side of its outline, the rest of the frame."""
    from scipy.ndimage import binary_dilation, binary_erosion

    edges = binary_dilation(car, iterations=2) & ~binary_erosion(car, iterations=2)
    return {"car": car & ~edges, "edges": edges, "background": ~car & ~edges}


def parse_cycles(text: str, ap: argparse.ArgumentParser) -> dict:
    """'blur_glossy=1.0,max_bounces=4' -> {'blur_glossy': 1.0, 'max_bounces': 4}"""
    out = {}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--cycles {text!r}: expected KEY=VALUE pairs separated by commas")
        try:
            out[key.strip()] = json.loads(value.lower() if value.lower() in ("true", "false") else value)
        except json.JSONDecodeError:
            out[key.strip()] = value  # an enum name
    return out


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
    ap.add_argument("--cycles", nargs="+", default=[""], metavar="KEY=VALUE[,KEY=VALUE]",
                    help="scene.cycles settings of the timed renders, one variant per argument (e.g. "
                         "blur_glossy=1.0,glossy_bounces=2; world.sample_map_resolution=2048 for the world's); '' is the "
                         "generator's; the reference keeps it")
    args = ap.parse_args()
    variants = [parse_cycles(v, ap) for v in args.cycles]
    denoise = []
    for d in args.denoise:
        q, _, pf = d.upper().partition(":")
        if q not in ("FAST", "BALANCED", "HIGH") or pf not in ("FAST", "ACCURATE", "NONE"):
            ap.error(f"--denoise {d!r}: expected QUALITY:PREFILTER, e.g. HIGH:ACCURATE")
        denoise.append((q, pf))
    w, h = (int(v) for v in args.resolution.split("x"))
    def renderer(spp: int, threshold: float = Recipe.noise_threshold, quality: str = "FAST", prefilter: str = "FAST",
                 pattern: str | None = None, cycles: dict | None = None):
        # views_per_car = views: one car and environment, so every frame is a steady-state
        # frame. A fresh renderer per sample count: Cycles' persistent session keeps the
        # sample count of its first render.
        recipe = Recipe(kind="pbr", seed=5, width=w, height=h, cars=("procedural:heldout",), samples=spp,
                        views_per_car=args.views, noise_threshold=threshold)
        r = make_renderer(recipe, threads=0)
        r.scene.cycles.denoising_quality, r.scene.cycles.denoising_prefilter = quality, prefilter
        if pattern:
            r.scene.cycles.sampling_pattern = pattern
        for key, value in (cycles or {}).items():
            # 'world.KEY' sets the world's Cycles settings (its light-sampling map), the rest scene.cycles
            target, name = (r.scene.world.cycles, key[6:]) if key.startswith("world.") else (r.scene.cycles, key)
            if not hasattr(target, name):
                raise SystemExit(f"--cycles: {'world' if target is not r.scene.cycles else 'scene'}.cycles "
                                 f"has no setting {name!r}")
            try:
                setattr(target, name, value)
            except (TypeError, ValueError) as exc:
                raise SystemExit(f"--cycles {key}={value!r}: {exc}") from None
        r.render_layers(0)  # builds the car, the sky and the light-sampling map
        return r

    r = renderer(args.reference)
    ref, regions = {}, {}
    t0 = time.perf_counter()
    for i in range(args.views):
        layers = r.render_layers(i)[0]
        ref[i] = linear_to_srgb(layers["rgb"])
        regions[i] = split_regions(layers["mask"][..., 0] > 0.5)
    ref_s = (time.perf_counter() - t0) / args.views
    print(f"reference: {args.reference} samples/pixel, {ref_s:.1f} s/frame", flush=True)
    results = []
    runs = ((s, t, d, p, c) for s in args.samples for t in args.noise_threshold for d in denoise
            for p in args.pattern for c in variants)
    for spp, threshold, (quality, prefilter), pattern, cycles in runs:
        r = renderer(spp, threshold, quality, prefilter, pattern, cycles)
        pattern = r.scene.cycles.sampling_pattern
        times, errs, parts = [], [], []
        for i in range(args.views):
            t = time.perf_counter()
            img = r.render_layers(i)[0]["rgb"]
            times.append(time.perf_counter() - t)
            sq = ((linear_to_srgb(img) - ref[i]) ** 2).mean(-1)
            errs.append(float(np.sqrt(sq.mean())))
            parts.append({k: float(sq[m].sum() / max(sq.sum(), 1e-20)) for k, m in regions[i].items()})
        results.append({"samples": spp, "noise_threshold": threshold, "denoise": f"{quality}:{prefilter}",
                        "pattern": pattern, "cycles": cycles,
                        "s_per_frame": float(np.mean(times)),
                        "rms_srgb": float(np.mean(errs)),
                        "error_share": {k: float(np.mean([p[k] for p in parts])) for k in REGIONS}})
        print(f"pbr {w}x{h} {spp:>3} samples/pixel (adaptive to {threshold:g}, OIDN {quality}:{prefilter}, {pattern}"
              f"{''.join(f', {k}={v}' for k, v in cycles.items())}): "
              f"{np.mean(times):.2f} s/frame, RMS error vs {args.reference} spp {np.mean(errs):.4f} (sRGB 0..1), "
              f"squared error on {' / '.join(REGIONS)}: "
              f"{' / '.join(f'{np.mean([p[k] for p in parts]):.2f}' for k in REGIONS)}",
              flush=True)
    print(json.dumps({"reference_s_per_frame": ref_s, "results": results}, indent=2))


if __name__ == "__main__":
    main()
