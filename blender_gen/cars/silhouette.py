"""Silhouettes of car meshes in metric orthographic views, and their pairwise IoU.

An orthographic view is the limit of one distant long-lens camera: pixels are metres, so
two cars compare by size as well as by shape. Views: side (X-Z; the two sides give
mirror images of one silhouette), end (Y-Z; front and rear alike) and top (X-Y). Every
car is placed with its footprint centred and its tyres on the ground, as `build_car` makes
it; imported models are normalised the same way by the importer.
"""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from ..geometry import Mesh

VIEWS = ("side", "end", "top")
# Canvas per view in metres (horizontal, vertical), centred horizontally; side/end rest on z = 0.
_EXTENT = {"side": (7.0, 3.0), "end": (3.0, 3.0), "top": (7.0, 3.0)}
_AXES = {"side": (0, 2), "end": (1, 2), "top": (0, 1)}


def silhouettes(parts: dict[str, Mesh] | Mesh, pixel: float = 0.02) -> dict[str, np.ndarray]:
    """Boolean masks per view at `pixel` metres per pixel."""
    meshes = [parts] if isinstance(parts, Mesh) else list(parts.values())
    out = {}
    for view in VIEWS:
        (ew, eh), (a, b) = _EXTENT[view], _AXES[view]
        w, h = int(round(ew / pixel)), int(round(eh / pixel))
        img = Image.new("1", (w, h), 0)
        draw = ImageDraw.Draw(img)
        for m in meshes:
            if not len(m.faces):
                continue
            p = m.verts[m.faces]  # (F, k, 3)
            u = (p[..., a] + 0.5 * ew) / pixel
            v = (eh - p[..., b]) / pixel if view != "top" else (0.5 * eh - p[..., b]) / pixel
            for fu, fv in zip(u.tolist(), v.tolist()):
                draw.polygon(list(zip(fu, fv)), fill=1)
        out[view] = np.asarray(img, dtype=bool)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 1.0


def pair_iou(a: dict[str, np.ndarray], b: dict[str, np.ndarray], views: tuple[str, ...] = VIEWS) -> float:
    """Mean IoU over the views."""
    return float(np.mean([iou(a[v], b[v]) for v in views]))


def iou_matrix(sils: list[dict[str, np.ndarray]], views: tuple[str, ...] = VIEWS) -> np.ndarray:
    n = len(sils)
    m = np.eye(n)
    for i in range(n):
        for j in range(i + 1, n):
            m[i, j] = m[j, i] = pair_iou(sils[i], sils[j], views)
    return m


def diversity(names: list[str], categories: list[str], m: np.ndarray) -> dict:
    """Within/across-category medians, the closest pair, and two leave-one-out category
    accuracies (are categories separable by their silhouettes?): by the nearest model, and by
    the highest mean IoU with a category's members."""
    n = len(names)
    iu = np.triu_indices(n, 1)
    same = np.array([categories[i] == categories[j] for i, j in zip(*iu)])
    vals = m[iu]
    k = int(np.argmax(vals))
    off = m - 2 * np.eye(n)
    nn = off.argmax(axis=1)
    correct = [categories[i] == categories[int(nn[i])] for i in range(n)]
    cats = sorted(set(categories))

    def nearest_category(i: int) -> str:  # highest mean IoU with a category's other members
        means = {c: np.mean([m[i, j] for j in range(n) if j != i and categories[j] == c]) for c in cats
                 if any(j != i and categories[j] == c for j in range(n))}
        return max(means, key=means.get)

    by_mean = [categories[i] == nearest_category(i) for i in range(n)]
    per_cat = {}
    for c in sorted(set(categories)):
        idx = [i for i in range(n) if categories[i] == c]
        sub = [m[i, j] for a, i in enumerate(idx) for j in idx[a + 1:]]
        per_cat[c] = {"models": len(idx), "median_iou": float(np.median(sub)) if sub else None,
                      "nn_accuracy": float(np.mean([correct[i] for i in idx])),
                      "mean_accuracy": float(np.mean([by_mean[i] for i in idx]))}
    return {
        "models": n,
        "within_median": float(np.median(vals[same])) if same.any() else None,
        "across_median": float(np.median(vals[~same])) if (~same).any() else None,
        "closest_pair": [names[iu[0][k]], names[iu[1][k]], float(vals[k])],
        "pairs_above_0.93": int(np.sum(vals > 0.93)),
        "nn_category_accuracy": float(np.mean(correct)),
        "mean_category_accuracy": float(np.mean(by_mean)),
        "per_category": per_cat,
    }
