"""Trainer benchmark: iterations/s and peak memory at 128x256, and data-loader throughput.

Each model configuration runs in its own process so its peak RSS is its own. Prints
measured figures; nothing is asserted. Usage: python bench/bench_train.py
On a GPU: python bench/bench_train.py --device cuda --size 512x256 --kinds iae cyclegan munit
(float32 weights and activations, as bench/objective_sweep.py trains; peak GPU memory is reported).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


# (preset, overrides, objective) per model kind and width: "paper" widths and cpu-small-like narrow
# ones. The Intrinsic Autoencoder at the paper's widths trains the default objective (what
# `reproduce --budget gpu` trains: the shader R) or the paper's own ("paper-objective", its pix2pixHD R).
WIDTHS = {
    ("iae", "paper"): ("paper", [], "default"),
    ("iae", "cpu-small"): ("cpu-small", [], None),
    ("iae", "paper-objective"): ("paper", [], None),
    ("cyclegan", "paper"): ("cyclegan", [], None),
    ("cyclegan", "cpu-small"): ("cyclegan", ["cyclegan.ngf=16", "cyclegan.n_blocks=4", "cyclegan.ndf=16"], None),
    ("munit", "paper"): ("munit", [], None),
    ("munit", "cpu-small"): ("munit", ["munit.dim=16", "munit.n_res=2", "munit.mlp_dim=64", "munit.d_ndf=16"], None),
}


def one(config: str, steps: int, h: int, w: int, kind: str, device: str = "cpu") -> dict:
    import torch

    from train.config import load_config, objective_overrides
    from train.loop import build_optimisation, discriminator_step, generator_step
    from train.model import build_model

    preset, extra, objective = WIDTHS[(kind, config)]
    if objective:
        extra = [*extra, *objective_overrides(preset, objective)]
    cfg = load_config(preset, [f"data.height={h}", f"data.width={w}", "data.batch_size=1", *extra])
    torch.manual_seed(0)
    model = build_model(cfg).to(device)
    g, d, opts, _ = build_optimisation(cfg, model)
    opt_g, opt_d = opts["G"], opts["D"]
    m_s, i_r = torch.rand(1, 9, h, w, device=device) * 2 - 1, torch.rand(1, 3, h, w, device=device) * 2 - 1
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    for _ in range(3 if device.startswith("cuda") else 1):  # warm-up (cuDNN picks its kernels)
        out, _ = generator_step(model, opt_g, g, m_s, i_r)
        discriminator_step(model, opt_d, d, out)
    sync()
    t = time.perf_counter()
    for _ in range(steps):
        out, _ = generator_step(model, opt_g, g, m_s, i_r)
        discriminator_step(model, opt_d, d, out)
    sync()
    dt = time.perf_counter() - t
    r = {"config": config, "kind": kind, "resolution": f"{h}x{w}", "batch": 1, "device": device,
         "it_per_s": steps / dt, "params_M": sum(p.numel() for p in model.parameters()) / 1e6,
         "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if device.startswith("cuda"):
        r["gpu"] = torch.cuda.get_device_name()
        r["peak_gpu_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return r


def loader(n_samples: int, workers: int) -> dict:
    from train.data import IntrinsicsData, StepSampler, infinite_loader

    tmp = Path(tempfile.mkdtemp(prefix="iae_bench_data_"))
    subprocess.run([sys.executable, "-m", "blender_gen.cli", "intrinsics", "--out", str(tmp / "d"), "--count", "64",
                    "--workers", "2", "--quiet"], cwd=ROOT, check=True, capture_output=True)
    ds = IntrinsicsData(tmp / "d", 256, 512)
    batch = 4
    it = infinite_loader(ds, StepSampler(len(ds), batch, 0, 0), workers)
    for _ in range(4):  # let the workers start
        next(it)
    t = time.perf_counter()
    for _ in range(n_samples // batch):
        next(it)
    dt = time.perf_counter() - t
    return {"loader_workers": workers, "resolution": "256x512", "decoded_samples_per_s": n_samples / dt}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--one", nargs=5, metavar=("CONFIG", "STEPS", "H", "W", "KIND"))
    ap.add_argument("--kinds", nargs="+", default=["iae"])
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--size", default="256x128", help="WIDTHxHEIGHT of the timed steps")
    args = ap.parse_args()
    if args.one:
        c, s, h, w, k = args.one
        print(json.dumps(one(c, int(s), int(h), int(w), k, args.device)))
        return
    w, h = args.size.split("x")
    gpu = args.device.startswith("cuda")
    results = []
    for kind in args.kinds:
        for config in (c for k, c in WIDTHS if k == kind):
            steps = (50 if gpu else 3) if config.startswith("paper") else (200 if gpu else 20)
            proc = subprocess.run([sys.executable, __file__, "--one", config, str(steps), h, w, kind,
                                   "--device", args.device], capture_output=True, text=True, cwd=ROOT, check=True)
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            results.append(r)
            mem = f", peak GPU memory {r['peak_gpu_mib']:.0f} MiB" if gpu else ""
            print(f"train {kind:8s} {config:15s} widths, {w}x{h} (width x height) batch 1 on {args.device}: {r['it_per_s']:.2f} it/s, "
                  f"{r['params_M']:.1f} M parameters, peak RSS {r['peak_rss_mib']:.0f} MiB{mem}", flush=True)
    if args.kinds == ["iae"] and not gpu:
        r = loader(200, 2)
        results.append(r)
        print(f"data loader 256x512, 2 workers: {r['decoded_samples_per_s']:.1f} decoded intrinsics samples/s", flush=True)
    print(json.dumps({"machine": {"cpus": os.cpu_count()}, "results": results}, indent=2))


if __name__ == "__main__":
    main()
