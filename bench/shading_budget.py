"""What the shader's shading model can explain of a path-traced car, from Cycles' light layers.

The shading objective (train.shading) explains an image's luminance on the car as
lum(A) x SH(N) + g x lum(F): second-order spherical harmonics of the normals and one reflection
gain. On Cycles images with the true maps that fit leaves a residual of 30-36% of the mean
luminance. A PBR set with light layers (`iae-gen pbr`, every set since the light layers) splits the
image into diffuse_color x diffuse_shading + glossy + transmission + emission + environment, so
the residual can be taken apart, per image on the car (relative residual = mean |fit - target| /
mean target, least squares, luminance, linear light):

  diffuse shading   SH(N) fitted to lum(diffuse_shading): what shadows, occlusion and
                    interreflection cost a 9-coefficient lighting
  diffuse image     lum(A) x SH(N) fitted to lum(diffuse_color x diffuse_shading)
  image, no gloss   lum(A) x SH(N) + g lum(F) fitted to the image less its glossy layer
  image             lum(A) x SH(N) + g lum(F) fitted to lum(rgb_noisy): the shading terms' target

and each layer's share of the car's luminance.

    python bench/shading_budget.py DATA/pbr_with_light_layers --out results/shading_budget/budget.json \
        --picture results/shading_budget/layers.png
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from blender_gen.dataset import LIGHT_LAYERS, DatasetError, open_dataset
from train.shading import sh_basis

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709, linear light


def lum(x: np.ndarray) -> np.ndarray:
    return x @ LUMA


def fit(columns: list[np.ndarray], target: np.ndarray, ridge: float = 1e-6) -> np.ndarray:
    """The least-squares fit (p,) of `target` (p,) by the columns (p,) each."""
    a = np.stack(columns, 1)
    return a @ np.linalg.solve(a.T @ a + ridge * np.eye(a.shape[1]), a.T @ target)


def relative_residual(columns: list[np.ndarray], target: np.ndarray) -> float:
    """mean |fit - target| / mean |target|."""
    return float(np.mean(np.abs(fit(columns, target) - target)) / max(np.mean(np.abs(target)), 1e-12))


CAR = 0.99  # whole car pixels: the edge mixes the background in


def car_sh(sample: dict) -> tuple[np.ndarray, np.ndarray]:
    """The whole-car mask (H, W) and the SH basis (p, 9) of the unit normals on it."""
    on = sample["mask"][..., 0] >= CAR
    n = sample["normal"][on]
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)
    return on, sh_basis(torch.from_numpy(n.T.copy()).float()[None, :, :, None])[0, :, :, 0].numpy().T


def sh_fit_picture(sample: dict) -> np.ndarray:
    """The SH(N) fit of lum(diffuse_shading) on the car, as an (H, W) luminance (0 elsewhere)."""
    on, sh = car_sh(sample)
    out = np.zeros(on.shape)
    out[on] = fit(list(sh.T), lum(sample["diffuse_shading"][on]))
    return out


def picture(samples: list[dict], out: Path, scale: int = 2) -> None:
    """One row per sample: the image and its layers on the car, the SH fit and its error; labelled."""
    from PIL import Image, ImageDraw

    from blender_gen.conversions import linear_to_srgb

    titles = ["image (Cycles)", "diffuse colour x shading", "glossy", "emission", "diffuse shading",
              "SH(N) fit of it", "|fit - shading|"]
    rows = []
    for s in samples:
        on = (s["mask"][..., 0] >= CAR)[..., None]
        shade = lum(s["diffuse_shading"]) * on[..., 0]
        norm = max(float(np.percentile(shade[on[..., 0]], 99)), 1e-6)  # one scale for shading, fit and error
        fit = sh_fit_picture(s)
        grey = lambda x: np.repeat((x / norm).clip(0, 1)[..., None], 3, -1)  # noqa: E731
        cols = [s["rgb_noisy"], s["diffuse_color"] * s["diffuse_shading"] * on, s["glossy"] * on, s["emission"] * on]
        tiles = [linear_to_srgb(np.clip(c, 0, 1)) for c in cols] + [grey(shade), grey(fit), grey(np.abs(fit - shade) * on[..., 0])]
        rows.append(np.concatenate(tiles, 1))
    grid = (np.concatenate(rows, 0) * 255 + 0.5).astype(np.uint8)
    h, w = samples[0]["mask"].shape[:2]
    img = Image.fromarray(grid).resize((grid.shape[1] * scale, grid.shape[0] * scale), Image.NEAREST)
    head = 16
    sheet = Image.new("RGB", (img.width, img.height + head), (255, 255, 255))
    sheet.paste(img, (0, head))
    draw = ImageDraw.Draw(sheet)
    for k, t in enumerate(titles):
        draw.text((k * w * scale + 3, 2), t, fill=(0, 0, 0))
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)


def budget(sample: dict) -> dict[str, float]:
    on, sh = car_sh(sample)
    a, f = lum(sample["albedo"][on]), lum(sample["reflection"][on])
    shading = lum(sample["diffuse_shading"][on])
    diffuse = lum(sample["diffuse_color"][on] * sample["diffuse_shading"][on])
    image = lum(sample["rgb_noisy"][on])
    glossy = lum(sample["glossy"][on])
    sh_cols = list(sh.T)
    total = max(float(image.mean()), 1e-12)
    return {
        "pixels": int(on.sum()),
        "residual_diffuse_shading": relative_residual(sh_cols, shading),
        "residual_diffuse_image": relative_residual([a * c for c in sh_cols], diffuse),
        "residual_image_without_glossy": relative_residual([a * c for c in sh_cols] + [f], image - glossy),
        "residual_image": relative_residual([a * c for c in sh_cols] + [f], image),
        "share_diffuse": float(diffuse.mean()) / total,
        "share_glossy": float(glossy.mean()) / total,
        "share_transmission": float(lum(sample["transmission"][on]).mean()) / total,
        "share_environment": float(lum(sample["environment"][on]).mean()) / total,
        "share_emission": float(lum(sample["emission"][on]).mean()) / total,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="a PBR set with light layers")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--min-pixels", type=int, default=200, help="skip samples with fewer whole car pixels")
    ap.add_argument("--out", type=Path, default=None, help="summary JSON (refused if it exists)")
    ap.add_argument("--picture", type=Path, default=None, help="a labelled PNG of the first --rows samples' layers")
    ap.add_argument("--rows", type=int, default=4)
    a = ap.parse_args()
    ds = open_dataset(a.data, kinds=("pbr",))
    missing = [k for k in LIGHT_LAYERS if k not in ds.layers]
    if missing:
        raise SystemExit(f"{a.data}: no {', '.join(missing)} layer(s); made before the light layers? "
                         "render a PBR set with this version of iae-gen")
    if a.out is not None and a.out.exists():
        raise SystemExit(f"{a.out}: exists; choose another --out")
    rows, shown = [], []
    for i in tqdm(range(min(len(ds), a.limit or len(ds))), desc="budget", unit="sample"):
        s = ds.load(i, ["normal", "albedo", "reflection", "mask", *LIGHT_LAYERS])
        if int((s["mask"][..., 0] >= CAR).sum()) < a.min_pixels:
            continue
        rows.append({"index": ds.rows[i]["index"], **budget(s)})
        if len(shown) < a.rows:
            shown.append(s)
    if not rows:
        raise DatasetError(f"{a.data}: no sample has {a.min_pixels} whole car pixels")
    keys = [k for k in rows[0] if k not in ("index", "pixels")]
    summary = {"data": a.data.name, "resolution": ds.info.get("resolution"), "samples": len(rows),
               "recipe": ds.info.get("recipe"),
               "mean": {k: round(float(np.mean([r[k] for r in rows])), 4) for k in keys},
               "median": {k: round(float(np.median([r[k] for r in rows])), 4) for k in keys}, "rows": rows}
    for k in keys:
        print(f"{k:<32} mean {summary['mean'][k]:.3f}  median {summary['median'][k]:.3f}")
    if a.picture is not None:
        picture(shown, a.picture)
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
