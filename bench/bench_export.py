"""Frames per second of the exported renderer R: PyTorch eager vs ONNX Runtime (CPU), and CUDA
eager where a GPU is present. R has the paper preset's architecture (global generator + local
enhancer, r_ngf 32) with freshly initialised weights: speed does not depend on the weights.
Prints measured figures; asserts nothing.
Usage: python bench/bench_export.py [--config paper] [--size 512x256] [--batches 1 8] [--seconds 10]
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import torch


def timed(fn, batch: int, seconds: float) -> float:
    fn()  # warm-up: allocations, oneDNN primitive creation
    n, t = 0, time.perf_counter()
    while time.perf_counter() - t < seconds or n < 2:
        fn()
        n += 1
    return n * batch / (time.perf_counter() - t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="paper")
    ap.add_argument("--size", default="512x256", help="WIDTHxHEIGHT")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--seconds", type=float, default=10.0, help="timing length of each figure")
    args = ap.parse_args()
    import onnxruntime as ort

    from train.config import load_config
    from train.export import _export_onnx, _Render, example_input
    from train.model import build_model

    w, h = (int(v) for v in args.size.split("x"))
    threads = torch.get_num_threads()
    cfg = load_config(args.config, [f"data.height={h}", f"data.width={w}"])
    torch.manual_seed(0)
    net = _Render(build_model(cfg)).eval()
    print(f"R of preset '{args.config}' at {w}x{h}, {sum(p.numel() for p in net.model.R.parameters()) / 1e6:.1f} M "
          f"parameters; {threads} CPU threads (torch), ONNX Runtime {ort.__version__}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "R.onnx"
        _export_onnx(net, torch.zeros(1, 9, h, w), path, {"input": "intrinsics", "output": "image"}, 17)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        print(f"{'runtime':<28}{'batch':>6}{'frames/s':>10}{'ms/frame':>10}")
        for batch in args.batches:
            x = example_input("R", batch, h, w)
            xt = torch.from_numpy(x)
            rows = []
            with torch.no_grad():
                rows.append(("PyTorch eager (CPU)", timed(lambda: net(xt), batch, args.seconds)))
            rows.append(("ONNX Runtime (CPU)", timed(lambda: session.run(None, {"intrinsics": x}), batch, args.seconds)))
            if torch.cuda.is_available():
                gnet, gx = net.cuda(), xt.cuda()

                def on_gpu():
                    with torch.no_grad():
                        gnet(gx)
                    torch.cuda.synchronize()

                rows.append((f"PyTorch eager ({torch.cuda.get_device_name()})", timed(on_gpu, batch, args.seconds)))
                net = net.cpu()
            for name, fps in rows:
                print(f"{name:<28}{batch:>6}{fps:>10.2f}{1000 / fps:>10.1f}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))
    main()
