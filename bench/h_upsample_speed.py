"""Time one of H's networks (forward and backward) with each upsampling layer, and count its
parameters.

The kinds are timed in turn within each round, so a CPU shared with other work slows them alike;
the median round is reported. Prints measured figures; nothing is asserted.
Usage: python bench/h_upsample_speed.py [--size 64x128] [--batch 4] [--preset cpu-small] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

KINDS = ("transposed", "resize", "subpixel")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="64x128", help="HEIGHTxWIDTH of H's input (default: the cpu budget's 64x128)")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--preset", default="cpu-small", help="config preset whose H widths are timed")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--repeats", type=int, default=5, help="passes per kind per round")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    try:
        h, w = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        sys.exit(f"--size: expected HEIGHTxWIDTH such as 64x128, got {args.size!r}")

    import torch

    from train.config import load_config
    from train.networks import ResnetGenerator

    torch.set_num_threads(args.threads)
    m = load_config(args.preset, []).model
    nets = {}
    for kind in KINDS:
        torch.manual_seed(0)
        nets[kind] = ResnetGenerator(3, 3, ngf=m.h_ngf, n_down=m.h_downsample, n_blocks=m.h_blocks, upsample=kind)
    x = torch.randn(args.batch, 3, h, w, generator=torch.Generator().manual_seed(0))
    for net in nets.values():  # warm-up
        net(x).mean().backward()
    times: dict[str, list[float]] = {k: [] for k in KINDS}
    for _ in range(args.rounds):
        for kind, net in nets.items():
            t = time.perf_counter()
            for _ in range(args.repeats):
                net(x).mean().backward()
            times[kind].append((time.perf_counter() - t) / args.repeats)
    base = statistics.median(times["transposed"])
    rows = [{"upsample": k, "params": sum(p.numel() for p in nets[k].parameters()),
             "ms": 1000 * statistics.median(times[k]), "relative": statistics.median(times[k]) / base} for k in KINDS]
    print(f"one H network ({args.preset} widths: ngf {m.h_ngf}, {m.h_blocks} blocks), batch {args.batch} at "
          f"{h}x{w}, forward + backward, {args.threads} thread(s), median of {args.rounds} rounds")
    print("| upsampling | parameters | ms per pass | x transposed |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {r['upsample']} | {r['params']:,} | {r['ms']:.1f} | {r['relative']:.2f} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"preset": args.preset, "size": f"{h}x{w}", "batch": args.batch,
                                         "threads": args.threads, "cpu_count": os.cpu_count(), "rows": rows},
                                        indent=1) + "\n")


if __name__ == "__main__":
    main()
