"""Import real car models (glTF/GLB, OBJ+MTL, .blend) as catalogue-like part meshes (bpy).

The model is read into Blender, every face is given a part by the rules (see `rules.py`),
and the result is normalised: forward axis to +X, up to +Z, centred on the origin, ground
at z = 0, scaled to the rules' length. The imported objects are then removed again; the
renderer builds its own part objects from the returned meshes, exactly as for
procedural cars. A .blend is appended through the library API, which never runs the
scripts or drivers a file may carry.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Mesh
from .faces import read_car
from .rules import SPLIT_PARTS, ModelSettings, Rules, RulesError, rule_labels, split_car
_AXIS = {"+X": (0, 1.0), "-X": (0, -1.0), "+Y": (1, 1.0), "-Y": (1, -1.0), "+Z": (2, 1.0), "-Z": (2, -1.0)}


@dataclass
class ImportedModel:
    name: str
    category: str
    parts: dict[str, Mesh]
    face_counts: dict[str, int]
    unmatched: int  # faces that fell to the default part



def _rotation(forward: str, up: str) -> np.ndarray:
    """Rows map model axes to the car frame: forward -> +X, up -> +Z, left = up x forward -> +Y."""
    f = np.zeros(3)
    f[_AXIS[forward][0]] = _AXIS[forward][1]
    u = np.zeros(3)
    u[_AXIS[up][0]] = _AXIS[up][1]
    return np.stack([f, np.cross(u, f), u])


def model_files(path: str | Path) -> list[Path]:
    """A car's files: one model file, or several joined by '+' (a body and its wheels)."""
    from ..recipe import companion_files

    files = split_car(path)
    for f in files:
        if not f.is_file():
            raise RulesError(f"--cars {f}: no such model file")
        try:
            companion_files(f)  # before Blender's importer could read a file outside the model's folder
        except ValueError as exc:
            raise RulesError(str(exc)) from None
    return files


def import_model(path: str | Path, rules: Rules) -> ImportedModel:
    files = model_files(path)
    if rules.auto:
        from .labeller import infer

        table, _ = read_car(files)
        lab = infer(table)
        settings = ModelSettings(forward=lab.forward, up=lab.up, length=lab.length, category=lab.category)
        return _normalise(files[0], settings, table.tris, table.normals, lab.labels, int((lab.evidence == "default").sum()))
    settings = rules.settings_for(files[0])
    table, _ = read_car(files, settings.forward, settings.up)
    labels, rule_hits = rule_labels(table, rules, settings.default_part, files[0], settings.up)
    if sum(n for idx, n in rule_hits.items() if idx) == 0:
        raise RulesError(f"{path}: no rule of {rules.path} matched any face (all {len(labels)} faces would be "
                         f"'{settings.default_part}'); check the object names, materials or palette ranges")
    return _normalise(files[0], settings, table.tris, table.normals, labels, rule_hits.get(0, 0))


def _normalise(path: Path, settings, tris: np.ndarray, normals: np.ndarray, labels: np.ndarray,
               unmatched: int) -> ImportedModel:
    rot = _rotation(settings.forward, settings.up)
    pts = tris.reshape(-1, 3) @ rot.T
    nrm = normals.reshape(-1, 3) @ rot.T
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = settings.length / max(hi[0] - lo[0], 1e-9)
    pts = (pts - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])) * scale
    pts = pts.reshape(-1, 3, 3)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-9)
    nrm = nrm.reshape(-1, 3, 3)
    # split parts that the rules leave to position and facing (windows, bumpers)
    centres = pts.mean(axis=1)
    face_n = np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0])
    face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-12)
    labels = labels.copy()
    win = labels == "windows"
    labels[win & (face_n[:, 0] > 0.35)] = "windshield"
    labels[win & (face_n[:, 0] < -0.35)] = "window_rear"
    labels[labels == "windows"] = "window_side"
    bump = labels == "bumpers"
    labels[bump & (centres[:, 0] >= 0)] = "bumper_front"
    labels[labels == "bumpers"] = "bumper_rear"
    parts = {}
    for part in sorted(set(labels)):
        ids = np.nonzero(labels == part)[0]
        faces = np.arange(3 * len(ids)).reshape(-1, 3)
        parts[part] = Mesh(pts[ids].reshape(-1, 3).astype(np.float64), faces, nrm[ids])
    counts = {k: int((labels == k).sum()) for k in parts}
    assert not set(parts) & set(SPLIT_PARTS)
    return ImportedModel(path.stem, settings.category, parts, counts, unmatched)
