"""Evaluation benchmark: images/s of FID feature extraction and of the decomposition
evaluation (H of a cpu-small run + scoring, and scoring alone) at 512x256 on this CPU, and the
seconds of one FID statistic from features (this project's nuclear-norm form against
torchmetrics' eigen-solve) at a CPU report's size (400 real, 200 fake) and at 2048 + 2048.
Prints measured figures. Usage: python bench/bench_eval.py [--images 48]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from eval.decomposition import score_predictions  # noqa: E402
from eval.fid import InceptionFeatures, extract, fid_from_features  # noqa: E402
from tests.train_helpers import tiny_intrinsics, tiny_photos  # noqa: E402
from train.config import load_config  # noqa: E402
from train.inference import decompose_images  # noqa: E402
from train.loop import fit  # noqa: E402


def _fid_torchmetrics(real: np.ndarray, fake: np.ndarray) -> float:
    import torch
    from torchmetrics.image.fid import _compute_fid

    r, f = torch.from_numpy(real).double(), torch.from_numpy(fake).double()
    return float(_compute_fid(r.mean(0), torch.cov(r.T), f.mean(0), torch.cov(f.T)))


def fid_statistic_seconds() -> dict:
    rng = np.random.default_rng(0)
    out = {}
    for n_real, n_fake in ((400, 200), (2048, 2048)):
        real = np.abs(rng.normal(size=(n_real, 2048)))  # pool features are non-negative
        fake = np.abs(rng.normal(0.1, 1.1, size=(n_fake, 2048)))
        row = {}
        for name, fn in (("nuclear_norm", fid_from_features), ("torchmetrics", _fid_torchmetrics)):
            t = time.perf_counter()
            value = fn(real, fake)
            row[name] = {"seconds": time.perf_counter() - t, "fid": value}
        print(f"FID statistic, {n_real} + {n_fake} features: nuclear norm {row['nuclear_norm']['seconds']:.2f} s, "
              f"torchmetrics {row['torchmetrics']['seconds']:.2f} s (values {row['nuclear_norm']['fid']:.4f} / "
              f"{row['torchmetrics']['fid']:.4f})", flush=True)
        out[f"{n_real}+{n_fake}"] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=int, default=48)
    args = ap.parse_args()
    n = args.images
    tmp = Path(tempfile.mkdtemp(prefix="iae_bench_eval_"))
    try:
        model = InceptionFeatures()
        imgs = np.random.default_rng(0).integers(0, 255, (n, 256, 512, 3), dtype=np.uint8)
        extract(model, iter(imgs[:8]), 8, progress=False)  # warm-up
        t = time.perf_counter()
        extract(model, iter(imgs), n, progress=False)
        fid_ips = n / (time.perf_counter() - t)
        print(f"FID/KID features (TF Inception-v3, 299x299, batch 16): {fid_ips:.1f} images/s", flush=True)

        pbr = tiny_intrinsics(tmp / "pbr", n=n, h=256, w=512, kind="pbr")
        cfg = load_config("cpu-small", ["data.workers=0", "run.grid_every=1000", "run.log_every=1000"])
        fit(tmp / "run", cfg, str(tiny_intrinsics(tmp / "intr", n=4)), str(tiny_photos(tmp / "ph")), max_steps=1,
            progress=False)
        t = time.perf_counter()
        decompose_images(tmp / "run", pbr, tmp / "pred", progress=False)
        score_predictions(pbr, tmp / "pred", progress=False)
        full_ips = n / (time.perf_counter() - t)
        t = time.perf_counter()
        score_predictions(pbr, tmp / "pred", progress=False)
        score_ips = n / (time.perf_counter() - t)
        print(f"decomposition evaluation 512x256 (cpu-small H at 64x128, upsampled, EXR out, scored): "
              f"{full_ips:.1f} images/s; scoring alone {score_ips:.1f} images/s", flush=True)
        fid_stat = fid_statistic_seconds()
        print(json.dumps({"fid_statistic": fid_stat, "fid_features_images_per_s": fid_ips, "decomposition_eval_images_per_s": full_ips,
                          "scoring_images_per_s": score_ips}, indent=2))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
