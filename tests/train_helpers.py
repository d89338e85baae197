"""Tiny datasets written directly in the dataset format (no Blender) for trainer tests."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from blender_gen.dataset import append_manifest, sample_filename, sha256_file, write_exr


def tiny_intrinsics(root: Path, n: int = 4, h: int = 32, w: int = 64, seed: int = 0, kind: str = "intrinsics") -> Path:
    """Car-like blobs: an ellipse with smooth normals, flat albedo, a reflection gradient.

    kind="pbr" adds an `rgb` layer (a shaded version of the same blob) for evaluation tests.
    """
    rng = np.random.default_rng(seed)
    (root / "samples").mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:h, 0:w]
    for i in range(n):
        cx, cy = w * rng.uniform(0.4, 0.6), h * rng.uniform(0.45, 0.6)
        rx, ry = w * rng.uniform(0.25, 0.35), h * rng.uniform(0.2, 0.3)
        u, v = (xx - cx) / rx, (yy - cy) / ry
        inside = u**2 + v**2 < 1
        nz = np.sqrt(np.clip(1 - u**2 - v**2, 0, 1))
        normal = np.stack([u, -v, nz], -1) * inside[..., None]
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-6)
        albedo = inside[..., None] * rng.uniform(0.05, 0.8, 3)
        refl = inside[..., None] * (0.3 + 0.5 * (1 - yy / h))[..., None] * np.array([0.8, 0.9, 1.0])
        layers = {"normal": normal, "albedo": albedo, "reflection": refl, "mask": inside[..., None].astype(float),
                  "material": inside[..., None] * 19.0}
        if kind == "pbr":
            shade = np.clip(normal[..., 2:3] * 0.8 + 0.2, 0, 1)
            layers["rgb"] = np.where(inside[..., None], albedo * shade + 0.3 * refl, np.array([0.4, 0.45, 0.5]))
        write_exr(root / sample_filename(i), layers)
        append_manifest(root / "manifest.jsonl", {"index": i, "file": sample_filename(i),
                                                   "sha256": sha256_file(root / sample_filename(i)),
                                                   "car": {"name": "blob", "category": "sedan"}, "paint": "x",
                                                   "envmap": {"name": "none", "rotation_deg": 0}})
    (root / "dataset.json").write_text(json.dumps({"kind": kind, "resolution": [w, h], "count": n,
                                                   "count_requested": n, "shard": [0, 1]}))
    return root


def tiny_photos(root: Path, n: int = 4, size=(90, 60), seed: int = 1) -> Path:
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = np.zeros((size[1], size[0], 3), np.uint8)
        img[...] = rng.integers(60, 200, 3)
        img[size[1] // 3: 2 * size[1] // 3, size[0] // 4: 3 * size[0] // 4] = rng.integers(0, 255, 3)
        Image.fromarray(img).save(root / f"photo_{i}.{'png' if i % 2 else 'jpg'}")
    return root


_COMMON = ["data.height=32", "data.width=64", "data.batch_size=2", "data.workers=0", "run.log_every=1",
           "run.grid_every=5", "run.checkpoint_every=3", "run.grid_samples=2"]
_NETS = {  # tiny networks, each kind in its own config section
    "iae": ["model.r_ngf=8", "model.r_downsample=2", "model.r_blocks=1", "model.h_ngf=8", "model.h_blocks=1",
            "model.d_ndf=8"],
    "cyclegan": ["cyclegan.ngf=8", "cyclegan.n_blocks=1", "cyclegan.ndf=8"],
    "munit": ["munit.dim=8", "munit.n_res=1", "munit.mlp_dim=16", "munit.d_ndf=8", "munit.d_layers=2"],
}


def tiny_overrides(kind: str = "iae") -> list[str]:
    return _COMMON + _NETS[kind]


def tiny_args(kind: str = "iae") -> list[str]:
    """The same overrides as `--set` options of `iae-train fit`."""
    return [a for item in tiny_overrides(kind) for a in ("--set", item)]


TINY = tiny_args("iae")


def tiny_fit(run: Path, intrinsics: Path, real: Path, steps: int, *extra: str, preset: str = "cpu-small",
             probe: Path | None = None) -> None:
    """Train a tiny run in this process, for tests whose subject is what reads or resumes it (a
    fresh process adds only start-up time there): `preset` with the tiny widths and `extra`."""
    from train.config import load_config
    from train.loop import fit

    kind = "iae" if preset == "cpu-small" else preset
    fit(run, load_config(preset, tiny_overrides(kind) + list(extra)), str(intrinsics), str(real), max_steps=steps,
        progress=False, probe=str(probe) if probe else None)
