"""How fast training can run on this CPU: bf16 autocast, channels-last, torch.compile, threads.

Each variant runs in its own process (a full generator + discriminator step of the Intrinsic
Autoencoder on synthetic tensors) and prints its measured it/s; nothing is asserted.
Usage: python bench/bench_cpu_speed.py [--config cpu-small] [--size 128x64] [--batch 4]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VARIANTS = {
    "fp32": {},
    "channels-last": {"channels_last": True},
    "bf16 autocast": {"bf16": True},
    "bf16 + channels-last": {"bf16": True, "channels_last": True},
    "torch.compile": {"compile": True},
    "1 thread": {"threads": 1},
}


def one(config: str, h: int, w: int, batch: int, steps: int, variant: dict) -> dict:
    import torch

    torch.set_num_threads(variant.get("threads", os.cpu_count() or 1))
    from eval.step_rate import time_steps

    # The docs name CPUs by this bench's fp32 reading, so its network stays the one those readings
    # were taken with (H's transposed layers) when the default changes.
    sets = [f"data.height={h}", f"data.width={w}", f"data.batch_size={batch}", "model.h_upsample=transposed"]
    rate, warm = time_steps(config, sets, steps, warmup=3, channels_last=variant.get("channels_last", False),
                            compile=variant.get("compile", False), bf16=variant.get("bf16", False))
    return {"it_per_s": rate, "images_per_s": rate * batch, "warmup_s": warm}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="cpu-small")
    ap.add_argument("--size", default="128x64", help="WIDTHxHEIGHT, as every size option")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.one:
        print(json.dumps(one(args.config, h, w, args.batch, args.steps, VARIANTS[args.one])))
        return
    print(f"{args.config} widths, {h}x{w}, batch {args.batch}, {os.cpu_count()} CPU threads available", flush=True)
    base = None
    for name in args.variants:
        proc = subprocess.run([sys.executable, __file__, "--config", args.config, "--size", args.size, "--batch",
                               str(args.batch), "--steps", str(args.steps), "--one", name],
                              capture_output=True, text=True, cwd=ROOT)
        if proc.returncode:
            print(f"  {name:22s} failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        base = base or r["it_per_s"]
        print(f"  {name:22s} {r['it_per_s']:6.2f} it/s  {r['images_per_s']:6.1f} images/s  "
              f"x{r['it_per_s'] / base:.2f}  (warm-up {r['warmup_s']:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
