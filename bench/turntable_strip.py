"""Every k-th frame of a turntable through R of several runs, beside the intrinsics and Cycles, labelled.

  iae-gen turntable --out tt/sedan --car sedan_a --frames 36 --resolution 256x128 --seed 7 --focal 35
  iae-gen turntable --out tt/sedan_pbr --car sedan_a --frames 36 --resolution 256x128 --seed 7 --focal 35 --pbr
  python bench/turntable_strip.py --intrinsics tt/sedan --pbr tt/sedan_pbr --every 6 --out strip.png \\
      "seed 21=runs/full_s21" "seed 22=runs/full_s22"

One row per frame: normal | albedo | reflection (as R gets them) | R of each run | Cycles, and with
--decompose H's normal and albedo of each run read from Cycles' frame (the round trip the other
way). R and H run at the runs' training size, as `iae-train render` and `decompose` do; every panel
is shown at that size.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    import torch
    from PIL import Image, ImageDraw

    from train.data import IntrinsicsData, RealImages
    from train.inference import load_run
    from train.video import display, side_by_side

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--intrinsics", required=True, help="the turntable's intrinsics (what R renders)")
    ap.add_argument("--pbr", default=None, help="its --pbr twin: Cycles' frames of the same path")
    ap.add_argument("--every", type=int, default=6)
    ap.add_argument("--decompose", action="store_true", help="also H's normal and albedo of Cycles' frames (needs --pbr)")
    ap.add_argument("--out", required=True)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_FOLDER")
    args = ap.parse_args()
    if args.decompose and not args.pbr:
        ap.error("--decompose reads Cycles' frames: give their set with --pbr")
    runs = [spec.split("=", 1) for spec in args.runs]
    models = [(label, *load_run(Path(run))[:2]) for label, run in runs]
    h, w = models[0][1].data.height, models[0][1].data.width
    data = IntrinsicsData(Path(args.intrinsics), h, w)
    cycles = RealImages(Path(args.pbr), h, w) if args.pbr else None
    titles = ["normal", "albedo", "reflection"] + [f"R, {label}" for label, _, _ in models] + (["Cycles"] if cycles else [])
    if args.decompose:
        titles += [f"H {what}, {label}" for label, _, _ in models for what in ("normal", "albedo")]
    rows = []
    with torch.no_grad():
        for i in range(0, len(data), args.every):
            m = data[(i, False)]
            panels = [display(m[k:k + 3]) for k in (0, 3, 6)]
            panels += [display(model.render(m[None])[0]) for _, _, model in models]
            if cycles is not None:
                img = cycles[(i, False)]
                panels.append(display(img))
                if args.decompose:
                    for _, _, model in models:
                        pred = model.decompose(img[None])[0]
                        panels += [display(pred[0:3]), display(pred[3:6])]
            rows.append(side_by_side(panels))
    body = np.concatenate([np.pad(r, ((0, 2), (0, 0), (0, 0)), constant_values=255) for r in rows])
    sheet = Image.new("RGB", (body.shape[1], body.shape[0] + 14), (255, 255, 255))
    sheet.paste(Image.fromarray(body), (0, 14))
    draw = ImageDraw.Draw(sheet)
    for k, t in enumerate(titles):
        draw.text((k * (w + 2) + 2, 1), t, fill=(0, 0, 0))
    sheet.save(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
