"""Decomposition errors against ground truth (the paper's Table 3), on the object mask.

Normals: angle between the normalised prediction and the truth (mean, median, % under
11.25 / 22.5 / 30 degrees). Albedo and reflection: L1 on the 0-255 sRGB scale (the paper's
scale) and on linear values; albedo also scale-invariantly (albedo is defined up to scale).
Speckle (not in the paper): the high-frequency energy (mean |Laplacian| inside the object) of
the predicted normals and albedo beside the truth's, so a hidden code in H's maps is a number.
Diffuse shading (not in the paper): where the predictions hold a `diffuse_shading` layer and the
ground truth holds Cycles' (PBR sets with light layers), the scale-invariant L1 on linear values
(shading is defined up to the light's scale) relative to the truth's mean, beside the same figure
for a flat shading, the bar any prediction must beat.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from blender_gen.conversions import linear_to_srgb
from blender_gen.dataset import DatasetError, atomic_write_bytes, atomic_write_json, open_dataset

THRESHOLDS = (11.25, 22.5, 30.0)


def normal_angles(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Angles in degrees between (N, 3) predictions (normalised here) and unit truths."""
    p = pred / np.maximum(np.linalg.norm(pred, axis=-1, keepdims=True), 1e-8)
    g = gt / np.maximum(np.linalg.norm(gt, axis=-1, keepdims=True), 1e-8)
    return np.degrees(np.arccos(np.clip(np.sum(p * g, axis=-1), -1.0, 1.0)))


def l1_srgb255(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean absolute difference of 8-bit sRGB values (both clipped to [0, 1] first)."""
    return float(np.mean(np.abs(linear_to_srgb(pred) - linear_to_srgb(gt))) * 255.0)


def l1_linear(pred: np.ndarray, gt: np.ndarray) -> float:
    return float(np.mean(np.abs(pred - gt)))


def scale_invariant_l1(pred: np.ndarray, gt: np.ndarray) -> float:
    """L1 after the least-squares scalar that best maps the prediction onto the truth."""
    denom = float(np.sum(pred * pred))
    alpha = float(np.sum(pred * gt)) / denom if denom > 0 else 0.0
    return float(np.mean(np.abs(alpha * pred - gt)))


def high_frequency(x: np.ndarray, on: np.ndarray) -> float:
    """Mean |Laplacian| of an (H, W, C) map over the interior of the mask `on` (pixels whose 4
    neighbours are also on, so the silhouette's edge does not count), averaged over channels."""
    p = np.pad(x.astype(np.float64), ((1, 1), (1, 1), (0, 0)), mode="edge")
    lap = np.abs(p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * p[1:-1, 1:-1]).mean(-1)
    m = np.pad(on, 1)
    inner = on & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    return float(lap[inner].mean()) if inner.any() else 0.0


SHADING = "diffuse_shading"


def shading_errors(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Scale-invariant L1 of (N, 3) linear diffuse shadings over the truth's mean: the
    prediction's, and a flat (constant) shading's, the bar it must beat."""
    mean = max(float(np.mean(np.abs(gt))), 1e-12)
    return {"shading_flat_si_rel_l1": scale_invariant_l1(np.ones_like(gt), gt) / mean,
            "shading_si_rel_l1": scale_invariant_l1(pred, gt) / mean}


def _unit(n: np.ndarray) -> np.ndarray:
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)


def score_sample(pred: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> tuple[dict, np.ndarray]:
    on = gt["mask"][..., 0] >= 0.5
    if not on.any():  # no car pixel to score: a broken or mislabelled sample
        raise DatasetError("the ground-truth mask is empty")
    ang = normal_angles(pred["normal"][on], gt["normal"][on])
    row = {
        "pixels": int(on.sum()),
        "normal_mean_deg": float(ang.mean()),
        "normal_median_deg": float(np.median(ang)),
        **{f"normal_under_{t:g}_pct": float((ang < t).mean() * 100.0) for t in THRESHOLDS},
        "albedo_l1_srgb255": l1_srgb255(pred["albedo"][on], gt["albedo"][on]),
        "albedo_l1_linear": l1_linear(pred["albedo"][on], gt["albedo"][on]),
        "albedo_si_l1_linear": scale_invariant_l1(pred["albedo"][on], gt["albedo"][on]),
        "reflection_l1_srgb255": l1_srgb255(pred["reflection"][on], gt["reflection"][on]),
        "reflection_l1_linear": l1_linear(pred["reflection"][on], gt["reflection"][on]),
        # speckle: normals as unit vectors, albedo in sRGB (as the eye and the L1 column see it)
        "normal_hf": high_frequency(_unit(pred["normal"]), on),
        "normal_hf_truth": high_frequency(_unit(gt["normal"]), on),
        "albedo_hf": high_frequency(linear_to_srgb(pred["albedo"]), on),
        "albedo_hf_truth": high_frequency(linear_to_srgb(gt["albedo"]), on),
    }
    if SHADING in pred and SHADING in gt:
        row.update(shading_errors(pred[SHADING][on], gt[SHADING][on]))
    return row, ang


def score_predictions(data: Path, predictions: Path, limit: int | None = None,
                      progress: bool = True) -> tuple[list[dict], dict]:
    """Per-sample rows and a summary: sample means, plus normal statistics over all pixels.

    Scores the first `limit` samples of `data` (all by default). Predictions made from
    another set are refused: their recorded source recipe, or a sample's source checksum,
    must match `data`. Samples without a prediction are counted in `missing_predictions`.
    """
    gt_ds = open_dataset(data, kinds=("pbr",))
    pred_ds = open_dataset(predictions, kinds=("predictions", "intrinsics", "pbr"))
    source_recipe = pred_ds.info.get("source_recipe")
    if source_recipe is not None and source_recipe != gt_ds.info.get("recipe"):
        raise DatasetError(f"{predictions}: made from {pred_ds.info.get('source')}, whose recipe differs from "
                           f"{data}'s (another seed or options); decompose --data itself")
    gt_rows = gt_ds.rows[:limit] if limit is not None else gt_ds.rows
    preds = {r["index"]: k for k, r in enumerate(pred_ds.rows)}
    # diffuse shading is scored where both sides hold it (sets made before the light layers do not)
    shading = SHADING in pred_ds.layers and SHADING in gt_ds.layers
    rows, all_angles = [], []
    missing = [r["index"] for r in gt_rows if r["index"] not in preds]
    if len(missing) == len(gt_rows):
        raise DatasetError(f"{predictions}: no prediction matches a sample index of {data}")
    for i, row in enumerate(tqdm(gt_rows, desc="score", unit="sample", disable=not progress)):
        if row["index"] not in preds:
            continue
        pred_row = pred_ds.rows[preds[row["index"]]]
        if pred_row.get("source_sha256", row["sha256"]) != row["sha256"]:
            raise DatasetError(f"{predictions}: sample {row['index']} was predicted from another image than "
                               f"{data}/{row['file']} (checksums differ)")
        gt = gt_ds.load(i, ["normal", "albedo", "reflection", "mask"] + [SHADING] * shading)
        pred = pred_ds.load(preds[row["index"]], ["normal", "albedo", "reflection"] + [SHADING] * shading)
        if pred["normal"].shape != gt["normal"].shape:
            raise DatasetError(f"{predictions}: sample {row['index']} is {pred['normal'].shape[1]}x"
                               f"{pred['normal'].shape[0]}, ground truth {gt['normal'].shape[1]}x{gt['normal'].shape[0]}")
        try:
            scores, ang = score_sample(pred, gt)
        except DatasetError as exc:  # name the sample score_sample cannot know
            raise DatasetError(f"--data {data}/{row['file']}: {exc} (sample {row['index']}); a Table-3 sample must "
                               "show its car: regenerate it or leave it out") from None
        rows.append({"index": row["index"], "car": row["car"]["name"], **scores})
        all_angles.append(ang)
    ang = np.concatenate(all_angles)
    metric_keys = [k for k in rows[0] if k not in ("index", "car", "pixels")]
    summary = {
        "samples": len(rows),
        "expected": len(gt_rows),
        "missing_predictions": len(missing),
        **{k: float(np.mean([r[k] for r in rows])) for k in metric_keys},
        "pixels": int(ang.size),
        "normal_median_deg_all_pixels": float(np.median(ang)),
        **{f"normal_under_{t:g}_pct_all_pixels": float((ang < t).mean() * 100.0) for t in THRESHOLDS},
        # speckle as a multiple of the truth's high-frequency energy (1 = as smooth as the truth)
        **{f"{k}_hf_ratio": float(np.mean([r[f"{k}_hf"] for r in rows]))
           / max(float(np.mean([r[f"{k}_hf_truth"] for r in rows])), 1e-12) for k in ("normal", "albedo")},
        "data": str(Path(data).resolve()),
        "predictions": str(Path(predictions).resolve()),
    }
    if SHADING in pred_ds.layers and not shading:
        summary["shading_note"] = f"{data} holds no {SHADING} layer (made before the light layers): shading not scored"
    return rows, summary


def write_results(rows: list[dict], summary: dict, out: Path) -> tuple[Path, Path]:
    """`out` is the summary JSON; the per-sample CSV goes beside it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    csv_path = out.with_suffix(".csv")
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(csv_path, buf.getvalue().encode())
    atomic_write_json(out, summary)
    return out, csv_path


def format_table(summary: dict) -> str:
    return "\n".join([
        f"decomposition errors over {summary['samples']} samples ({summary['pixels']} object pixels)",
        f"  normal      mean {summary['normal_mean_deg']:.2f} deg, median {summary['normal_median_deg']:.2f} deg, "
        + ", ".join(f"<{t:g} deg {summary[f'normal_under_{t:g}_pct']:.1f}%" for t in THRESHOLDS),
        f"  albedo      L1 {summary['albedo_l1_srgb255']:.2f} (0-255 sRGB), {summary['albedo_l1_linear']:.4f} (linear), "
        f"scale-invariant {summary['albedo_si_l1_linear']:.4f}",
        f"  reflection  L1 {summary['reflection_l1_srgb255']:.2f} (0-255 sRGB), {summary['reflection_l1_linear']:.4f} (linear)",
    ] + ([f"  speckle     high-frequency energy x the truth's: normals {summary['normal_hf_ratio']:.2f}, "
          f"albedo {summary['albedo_hf_ratio']:.2f}"] if "normal_hf_ratio" in summary else [])
        + ([f"  shading     scale-invariant L1 / the truth's mean {summary['shading_si_rel_l1']:.4f} "
            f"(a flat shading: {summary['shading_flat_si_rel_l1']:.4f})"] if "shading_si_rel_l1" in summary else [])
        + ([f"  shading     {summary['shading_note']}"] if "shading_note" in summary else []))


def summary_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())
