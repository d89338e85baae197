"""Why the shader R's input sensitivity reads below 1: R, its lighting, or H's maps?

On car pixels the shader R is analytic (SH shading of the normals x albedo + gain x reflection), so
its input sensitivity on the probe (`train.probe.input_sensitivity`) depends only on the lighting it
renders under: by default the mean of the bank of lightings fitted to real images *through H's
maps*. This script renders the probe's true intrinsics under other lightings and measures H's
albedo level, to say where the shortfall comes from:

- `bank_mean`: as the probe measures it (the bank's mean lighting);
- `own_fit`: each probe image's own lighting, fitted by least squares with its true maps;
- `probe_mean_fit`: one lighting for every sample, the mean of those fits;
- the ambient (SH band 0) of the bank, of the fits through H's maps and of the fits through the
  true maps, on the same probe images;
- H's albedo level (mean linear albedo on the car, per channel) on the run's real images against
  the training intrinsics' level, and what a per-channel correction by that ratio (training data
  only, no ground truth) does to the probe's albedo L1 and to R's sensitivity;
- the split between shading and reflection: the lightings fitted through H's maps on the real
  images again with the reflection gain held at the probe's true-map fits' mean (`refit_gain_fixed`),
  and the overall level: the real images' mean linear colour on H's car mask against R's renders
  of the training intrinsics under lightings drawn from the bank (`car_level`).

    python bench/r_sensitivity.py out/cpu21/runs/full --data out/cpu21/data --out r_sensitivity_s21.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from train.colour import srgb_decode, srgb_encode  # noqa: E402
from train.data import IntrinsicsData  # noqa: E402
from train.inference import load_run_checkpoint  # noqa: E402
from train.losses import linear_mean, masked_mean, object_mask  # noqa: E402
from train.probe import input_sensitivity, load_probe  # noqa: E402
from train.shading import fit_lighting, render_sh  # noqa: E402


def _lin(x: torch.Tensor) -> torch.Tensor:
    return srgb_decode((x + 1) / 2)


def _albedo_level(maps: torch.Tensor) -> torch.Tensor:
    """(3,) mean linear albedo on the object pixels of (n, 9, h, w) network-space stacks."""
    return linear_mean(maps[:, 3:6], object_mask(maps))


@torch.no_grad()
def measure(run: Path, data: Path, every: int = 10, real_limit: int = 200) -> dict | None:
    """The figures above for one run; None where R has no filled lighting bank (nothing to measure)."""
    cfg, model, step, _ = load_run_checkpoint(run)
    R = model.R
    if getattr(R, "bank", None) is None or int(R.bank_filled) == 0:
        return None
    h, w = cfg.data.height, cfg.data.width
    probe = load_probe(data / "eval", h, w)
    M, I, on = probe.maps, probe.images, probe.masks[:, 0] >= 0.5
    n = len(M)
    bank = R.bank[:int(R.bank_filled)]

    def sens(light: torch.Tensor | None) -> float:
        return input_sensitivity(R(M, light), I, on)

    lf, gf = fit_lighting(I, M[:, 0:3], M[:, 3:6], M[:, 6:9], on.unsqueeze(1))
    own = torch.cat([lf, gf.unsqueeze(-1)], -1)
    H = model.decompose(I)
    lh, _ = fit_lighting(I, H[:, 0:3], H[:, 3:6], H[:, 6:9], on.unsqueeze(1))

    # H's albedo level on the training real images against the training intrinsics'
    real = load_probe(data / "real", h, w, limit=real_limit)
    h_real = torch.cat([model.decompose(real.images[i:i + 16]) for i in range(0, len(real.images), 16)])
    ds = IntrinsicsData(data / "intrinsics", h, w)
    train = torch.stack([ds[(i, False)] for i in range(0, len(ds), every)])
    level_train, level_h = _albedo_level(train), _albedo_level(h_real)
    k = level_train / level_h
    a_cal = srgb_encode((_lin(H[:, 3:6]) * k.view(1, 3, 1, 1)).clamp(0, 1)) * 2 - 1
    cal_bank = bank.clone()
    cal_bank[..., :9] /= k.view(1, 3, 1)

    # the shading / reflection split: H's fits on the real images with the truth's reflection gain
    h_mask = object_mask(h_real)
    lr, gr = fit_lighting(real.images, h_real[:, 0:3], h_real[:, 3:6], h_real[:, 6:9], h_mask, gain=gf.mean(0))
    refit = torch.cat([lr, gr.unsqueeze(-1)], -1).clamp(-10, 10).mean(0, keepdim=True)
    # the overall level: R of the training intrinsics under drawn bank lightings against the real images
    drawn = bank[torch.randint(len(bank), (len(train),), generator=torch.Generator().manual_seed(0))]
    car = object_mask(train)
    lin = render_sh(train[:, 0:3], train[:, 3:6], train[:, 6:9], drawn[..., :9], drawn[..., 9])

    def l1(pred: torch.Tensor) -> float:
        return float(((pred - M[:, 3:6]).abs().mean(1) * 127.5)[on].mean())

    r3 = lambda t: [round(float(v), 3) for v in t]  # noqa: E731
    return {
        "run": str(run), "step": step, "weights": model.weights, "bank_size": int(R.bank_filled),
        "sensitivity": {
            "bank_mean": round(sens(None), 3),
            "own_fit": round(sens(own), 3),
            "probe_mean_fit": round(sens(own.mean(0, keepdim=True).expand(n, -1, -1)), 3),
            "bank_mean_corrected": round(sens(cal_bank.mean(0, keepdim=True).expand(n, -1, -1)), 3),
            "refit_gain_fixed": round(sens(refit.expand(n, -1, -1)), 3),
        },
        "reflection_gain": {"bank": r3(bank[..., 9].mean(0)), "probe_fit_through_truth": r3(gf.mean(0))},
        "refit_gain_fixed_ambient": r3(refit[0, :, 0]),
        "car_level": {"real_images_on_H_mask": r3(linear_mean(real.images, h_mask)),
                      "R_of_training_intrinsics_under_bank": r3(masked_mean(lin, car))},
        "ambient_sh0": {"bank": r3(bank[..., 0].mean(0)), "probe_fit_through_H": r3(lh[..., 0].mean(0)),
                        "probe_fit_through_truth": r3(lf[..., 0].mean(0))},
        "albedo_level": {"training_intrinsics": r3(level_train), "H_on_real_images": r3(level_h),
                         "correction": r3(k)},
        "probe_albedo_l1": {"H": round(l1(H[:, 3:6]), 2), "H_corrected": round(l1(a_cal), 2)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders of shader-R runs")
    ap.add_argument("--data", type=Path, nargs="+", required=True,
                    help="the reproduce data folder of each run (with eval/, real/, intrinsics/)")
    ap.add_argument("--out", type=Path, help="JSON file for the figures")
    args = ap.parse_args()
    if len(args.data) not in (1, len(args.runs)):
        raise SystemExit(f"--data: one folder, or one per run ({len(args.runs)}); got {len(args.data)}")
    torch.set_num_threads(1)
    rows = []
    for i, run in enumerate(args.runs):
        data = args.data[i if len(args.data) > 1 else 0]
        for sub in ("eval", "real", "intrinsics"):
            if not (data / sub).is_dir():
                raise SystemExit(f"--data {data}: no {sub}/ folder (expected a reproduce data folder)")
        row = measure(run, data)
        if row is None:
            print(f"{run}: skipped, R has no filled lighting bank (not a shader run, or no decomposition cycle)")
            continue
        rows.append(row)
        print(json.dumps(row))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
