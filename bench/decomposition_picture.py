"""A labelled picture of several runs' H on the same probe images, beside the ground truth.

    python bench/decomposition_picture.py --probe PBR_SET --out picture.png [--samples 4] [--scale 3] \
        LABEL=RUN_DIR [LABEL=RUN_DIR ...]

Per probe image one row: the image, then for normals, albedo and reflection the ground truth and
every run's prediction (moving-average weights where the run has them, as inference uses). Each
run's H sees the image at its training size; tiles are enlarged by --scale (nearest neighbour, so
speckle stays visible). Column titles name what each tile is.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from train.inference import load_run_checkpoint  # noqa: E402
from train.probe import load_probe  # noqa: E402


def tile(t: torch.Tensor) -> np.ndarray:
    return ((t.clamp(-1, 1) + 1) * 127.5 + 0.5).byte().permute(1, 2, 0).numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--probe", type=Path, required=True, help="a PBR set (images with their intrinsics)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--scale", type=int, default=3)
    args = ap.parse_args()
    from PIL import Image, ImageDraw

    torch.set_num_threads(1)
    preds, size = [], None
    for item in args.runs:
        label, _, path = item.partition("=")
        cfg, model, step, _ = load_run_checkpoint(Path(path))
        if size not in (None, (cfg.data.height, cfg.data.width)):
            sys.exit(f"{path}: trained at {cfg.data.height}x{cfg.data.width}, the others at {size[0]}x{size[1]}")
        size = (cfg.data.height, cfg.data.width)
        probe = load_probe(args.probe, *size, limit=args.samples)
        with torch.no_grad():
            preds.append((f"{label} (step {step})", model.decompose(probe.images)))
    h, w = size
    s = args.scale
    titles = ["image"]
    for layer in ("normal", "albedo", "reflection"):
        titles += [f"{layer}: truth"] + [f"{layer}: {label}" for label, _ in preds]
    rows = []
    for i in range(len(probe.images)):
        cols = [probe.images[i]]
        for sl in (slice(0, 3), slice(3, 6), slice(6, 9)):
            cols += [probe.maps[i, sl]] + [p[i, sl] for _, p in preds]
        rows.append(np.concatenate([tile(c) for c in cols], axis=1))
    grid = Image.fromarray(np.concatenate(rows, axis=0)).resize((len(titles) * w * s, len(rows) * h * s), Image.NEAREST)
    head = 14 * max(1, max(len(t) for t in titles) * 6 // (w * s) + 1)
    sheet = Image.new("RGB", (grid.width, grid.height + head), (255, 255, 255))
    sheet.paste(grid, (0, head))
    draw = ImageDraw.Draw(sheet)
    per_line = max(1, (w * s) // 6)
    for k, title in enumerate(titles):
        words, lines = title.split(), [""]
        for word in words:  # wrap titles to the tile width
            if len(lines[-1]) + len(word) + 1 > per_line and lines[-1]:
                lines.append(word)
            else:
                lines[-1] = f"{lines[-1]} {word}".strip()
        for j, line in enumerate(lines):
            draw.text((k * w * s + 3, 2 + 12 * j), line, fill=(0, 0, 0))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
