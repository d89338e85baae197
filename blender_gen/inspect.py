"""`iae-gen inspect`: summary, checksum verification and a preview grid (no bpy)."""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .conversions import preview_srgb8
from .dataset import LIGHT_LAYERS, DatasetError, recompose, open_dataset, read_exr, save_png, sha256_file


# Mean |sum of light layers - rgb_noisy| on the car over mean |rgb_noisy|: exact in Cycles, so what
# remains is each layer's rounding to half float (measured: below 0.1%)
RECOMPOSITION_TOLERANCE = 0.01


def inspect_dataset(root: Path, max_stats: int | None = None, progress: bool = True) -> dict:
    """Verify every sample and gather statistics. `problems` lists what is wrong."""
    ds = open_dataset(root)
    layers = ds.layers
    n_parts = len(ds.info.get("parts", [])) or None
    w, h = ds.resolution
    problems: list[str] = []
    bad_files: list[str] = []
    stats = {name: {"min": np.inf, "max": -np.inf, "sum": 0.0, "n": 0} for name in layers}
    unit_err, unit_n = 0.0, 0
    recomp_err: float | None = None  # PBR: the light layers' sum against rgb_noisy on the car
    expected = ds.info.get("count_requested", len(ds))
    shard = ds.info.get("shard", [0, 1])
    want = {i for i in range(expected) if i % shard[1] == shard[0]}
    have = [r["index"] for r in ds.rows]
    dupes = sorted(i for i, c in Counter(have).items() if c > 1)
    if dupes:
        problems.append(f"duplicate manifest rows for samples {dupes[:10]}")
    missing = sorted(want - set(have))
    if missing:
        problems.append(f"{len(missing)} sample(s) missing from the manifest, e.g. {missing[:10]}")
    for k, row in enumerate(tqdm(ds.rows, desc="inspect", unit="sample", disable=not progress)):
        path = ds.root / row["file"]
        if not path.exists():
            problems.append(f"{row['file']}: missing")
            bad_files.append(row["file"])
            continue
        if sha256_file(path) != row["sha256"]:
            problems.append(f"{row['file']}: checksum mismatch")
            bad_files.append(row["file"])
            continue
        if max_stats is not None and k >= max_stats:
            continue
        try:
            data = read_exr(path, layers)
        except DatasetError as exc:
            problems.append(str(exc))
            continue
        for name, arr in data.items():
            if arr.shape[:2] != (h, w):
                problems.append(f"{row['file']}: layer {name} is {arr.shape[1]}x{arr.shape[0]}, expected {w}x{h}")
            if not np.all(np.isfinite(arr)):
                problems.append(f"{row['file']}: layer {name} has non-finite values")
            s = stats[name]
            s["min"], s["max"] = min(s["min"], float(arr.min())), max(s["max"], float(arr.max()))
            s["sum"] += float(arr.sum(dtype=np.float64))
            s["n"] += arr.size
        if "mask" in data:  # the extra layers agree with the mask and their own ranges
            on, off = data["mask"][..., 0] > 0.5, data["mask"][..., 0] <= 0
            if "normal" in data and on.any():
                unit_err = max(unit_err, float(np.abs(np.linalg.norm(data["normal"][on], axis=-1) - 1).max()))
                unit_n += int(on.sum())
            if "depth" in data and ((data["depth"][on] <= 0).any() or (data["depth"][off] != 0).any()):
                problems.append(f"{row['file']}: depth is not positive on the car and 0 off it")
            if "part" in data and ((data["part"][on] < 1).any() or (n_parts and (data["part"] >= n_parts).any())):
                problems.append(f"{row['file']}: part indices outside 1..{(n_parts or 0) - 1} on the car")
            if "gloss" in data and ((data["gloss"] < 0).any() or (data["gloss"] > 1).any()):
                problems.append(f"{row['file']}: gloss outside [0, 1]")
        if set(LIGHT_LAYERS) <= set(data) and "mask" in data:
            car = data["mask"][..., 0] >= 1.0
            if car.any():
                ref = data["rgb_noisy"][car]
                rel = float(np.abs(recompose(data)[car] - ref).mean() / max(float(np.abs(ref).mean()), 1e-6))
                recomp_err = max(recomp_err or 0.0, rel)
                if rel > RECOMPOSITION_TOLERANCE:
                    problems.append(f"{row['file']}: the light layers add up to rgb_noisy on the car only within "
                                    f"{rel:.2%} (tolerance {RECOMPOSITION_TOLERANCE:.0%})")
    summary = {
        "root": str(ds.root),
        "kind": ds.kind,
        "resolution": [w, h],
        "samples": len(ds),
        "expected": len(want),
        "complete": not missing and not problems,
        "categories": dict(Counter(r.get("car", {}).get("category", "-") for r in ds.rows)),
        "cars": len({r.get("car", {}).get("name") for r in ds.rows} - {None}),
        "paints": dict(Counter(r.get("paint", "-") for r in ds.rows)),
        "envmaps": dict(Counter(r.get("envmap", {}).get("name", "-") for r in ds.rows)),
        "layers": {k: {"min": v["min"], "max": v["max"], "mean": v["sum"] / v["n"]} for k, v in stats.items() if v["n"]},
        "normal_unit_error_max": unit_err if unit_n else None,
        "recomposition_error_max": recomp_err,
        "problems": problems,
        "bad_files": bad_files,
    }
    return summary


def preview_grid(root: Path, out: Path, count: int = 6, skip: frozenset[str] = frozenset()) -> Path:
    """A PNG with one row per sample: (rgb,) normal, albedo, reflection in sRGB, then depth (near
    bright), part (a colour per part), gloss, and a PBR set's diffuse shading and glossy light where
    the set has them.

    Samples whose files are named in `skip` (failed verification) are left out.
    """
    ds = open_dataset(root)
    usable = [i for i, r in enumerate(ds.rows) if r["file"] not in skip]
    if not usable:
        raise DatasetError(f"{root}: no finished samples to preview")
    cols = [c for c in ("rgb", "normal", "albedo", "reflection", "depth", "part", "gloss", "diffuse_shading", "glossy")
            if c in ds.layers]
    picks = [usable[k] for k in np.linspace(0, len(usable) - 1, min(count, len(usable))).round().astype(int)]
    rows = []
    for i in picks:
        data = ds.load(int(i), cols)
        rows.append(np.concatenate([preview_srgb8(c, data[c]) for c in cols], axis=1))
    grid = _titled(np.concatenate(rows, axis=0), cols, rows[0].shape[1] // len(cols))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_png(out, grid)
    return out


def _titled(grid: np.ndarray, titles: list[str], col_width: int) -> np.ndarray:
    """The grid under a white band naming each column."""
    from PIL import Image, ImageDraw

    band = Image.new("RGB", (grid.shape[1], 14), (255, 255, 255))
    draw = ImageDraw.Draw(band)
    for k, title in enumerate(titles):
        draw.text((k * col_width + 3, 1), title.replace("_", " "), fill=(0, 0, 0))
    return np.concatenate([np.asarray(band), grid], axis=0)


def format_summary(s: dict) -> str:
    lines = [
        f"dataset   {s['root']}  ({s['kind']}, {s['resolution'][0]}x{s['resolution'][1]})",
        f"samples   {s['samples']} of {s['expected']}  {'complete' if s['complete'] else 'INCOMPLETE'}",
        f"cars      {s['cars']} models; categories " + ", ".join(f"{k} {v}" for k, v in sorted(s["categories"].items())),
        "paints    " + ", ".join(f"{k} {v}" for k, v in sorted(s["paints"].items())),
        "envmaps   " + ", ".join(f"{k} {v}" for k, v in sorted(s["envmaps"].items())),
        "layer                min        max       mean",
    ]
    for name, v in s["layers"].items():
        lines.append(f"{name:<16} {v['min'] + 0.0:>9.4f} {v['max']:>10.4f} {v['mean']:>10.4f}")  # + 0.0: no "-0.0000"
    if s["normal_unit_error_max"] is not None:
        lines.append(f"normals   max | |n| - 1 | on the mask: {s['normal_unit_error_max']:.2e}")
    if s.get("recomposition_error_max") is not None:
        lines.append(f"light     diffuse_color x diffuse_shading + glossy + transmission + emission + environment "
                     f"= rgb_noisy on the car within {s['recomposition_error_max']:.3%} (worst sample)")
    for p in s["problems"]:
        lines.append(f"PROBLEM   {p}")
    return "\n".join(lines)
