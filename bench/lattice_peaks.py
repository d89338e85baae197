"""How much of H's maps is a pattern locked to the decoder's pixel lattice (the checkerboard).

    python bench/lattice_peaks.py --probe PBR_SET [--samples 48] [--json out.json] LABEL=RUN_DIR ...

H doubles the resolution h_downsample times; a stride-2 transposed convolution gives even and odd
pixels different numbers of kernel taps, which stamps a pattern of period 2, 4, ... on its output
(Odena et al., 2016). Such a pattern puts its power at the frequencies k/P of the lattice (period
P = 2 ** h_downsample), where images of cars have no peaks. Per map, the figure is the power at those
frequencies (Hann-windowed spectra, averaged over samples and channels) over the median power of the
frequencies around each: 1 = no peak, as in the ground truth; 3 = three times its surroundings.
Each run's H sees the images at its training size (moving-average weights where the run has them).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from train.inference import load_run_checkpoint  # noqa: E402
from train.networks import CHANNELS  # noqa: E402
from train.probe import load_probe  # noqa: E402

MAPS = {"normal": CHANNELS["N"], "albedo": CHANNELS["A"], "reflection": CHANNELS["F"]}


def upsampling(cfg) -> tuple[str, int]:
    """How a run's decomposer doubles its resolution, and the period of the lattice that leaves."""
    if cfg.model.kind == "cyclegan":
        return "transposed", 2 ** cfg.cyclegan.n_down
    if cfg.model.kind == "munit":
        return "resize (MUNIT's)", 2 ** cfg.munit.n_down
    return cfg.model.h_upsample, 2 ** cfg.model.h_downsample


def lattice_peak_ratio(x: torch.Tensor, period: int) -> float:
    """Mean, over the lattice frequencies (k h / P, l w / P) other than 0, of the power there over the
    median power of the ring of frequencies two bins away; x is (n, c, h, w)."""
    n, c, h, w = x.shape
    window = torch.hann_window(h, periodic=False)[:, None] * torch.hann_window(w, periodic=False)[None, :]
    x = (x - x.mean(dim=(-2, -1), keepdim=True)) * window
    power = (torch.fft.fft2(x.double()).abs() ** 2).mean(dim=(0, 1))
    ring = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3) if max(abs(dy), abs(dx)) == 2]
    ratios = []
    for ky in range(period):
        for kx in range(period):
            if ky == kx == 0:
                continue
            y, xx = ky * h // period, kx * w // period
            around = torch.stack([power[(y + dy) % h, (xx + dx) % w] for dy, dx in ring])
            ratios.append(float(power[y, xx] / around.median()))
    return sum(ratios) / len(ratios)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--probe", type=Path, required=True, help="a PBR set (images with their intrinsics)")
    ap.add_argument("--samples", type=int, default=48)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows, probes, truth = [], {}, {}
    for item in args.runs:
        label, _, path = item.partition("=")
        if not path:
            sys.exit(f"{item!r}: expected LABEL=RUN_DIR")
        cfg, model, step, _ = load_run_checkpoint(Path(path))
        upsample, period = upsampling(cfg)
        size = (cfg.data.height, cfg.data.width)
        if size not in probes:  # runs trained at one size share the probe's images and maps
            probes[size] = load_probe(args.probe, *size, limit=args.samples)
        probe = probes[size]
        with torch.no_grad():
            pred = model.decompose(probe.images)
        key = (*size, period)
        if key not in truth:
            truth[key] = {m: lattice_peak_ratio(probe.maps[:, sl], period) for m, sl in MAPS.items()}
        rows.append({"label": label, "run": path, "step": step, "upsample": upsample,
                     "period": period, "size": f"{cfg.data.width}x{cfg.data.height}",
                     **{m: lattice_peak_ratio(pred[:, sl], period) for m, sl in MAPS.items()},
                     "truth": truth[key]})
    print(f"lattice peaks of H's maps on {args.probe} ({len(probe.images)} images): power at the lattice's "
          "frequencies over that around them (1 = no peak)\n")
    print("| run | step | H's upsampling | normal | albedo | reflection | truth: normal / albedo / reflection |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        t = r["truth"]
        print(f"| {r['label']} | {r['step']} | {r['upsample']} | {r['normal']:.2f} | {r['albedo']:.2f} | "
              f"{r['reflection']:.2f} | {t['normal']:.2f} / {t['albedo']:.2f} / {t['reflection']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps({"probe": str(args.probe), "samples": len(probe.images), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
