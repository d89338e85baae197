"""A dataset for tools that cannot read multi-layer EXR: one file per sample and layer.

`npy`: float32 (H, W, C) arrays in the dataset's own units, exactly as `Dataset.load` returns them.
`png16`: 16-bit PNGs (pypng), with the encoding of each layer written to `conversion.json`:
normals as (n + 1) / 2, colours in *linear* light clipped to [0, 1] (the rgb layer's highlights
above 1 are clipped), the mask as coverage, the material as its integer id.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .dataset import DatasetError, atomic_target, atomic_write_json, folder_is_empty, locked_folder, open_dataset

FORMATS = ("npy", "png16")
PNG16_ENCODING = {
    "normal": "uint16 = round((n + 1) / 2 * 65535); n = v / 65535 * 2 - 1 (camera space; 0 off the object reads as 32768)",
    "albedo": "uint16 = round(clip(linear, 0, 1) * 65535); linear light, not sRGB",
    "reflection": "uint16 = round(clip(linear, 0, 1) * 65535); linear light, not sRGB",
    "rgb": "uint16 = round(clip(linear, 0, 1) * 65535); linear light, not sRGB; values above 1 clipped",
    "mask": "uint16 = round(coverage * 65535), grey",
    "material": "uint16 = material id (0 background, 1-18 part materials, 19 body paint), grey",
    "depth": "uint16 = round(metres * 1000), millimetres along the view axis (0 on the background; at most 65.535 m)",
    "part": "uint16 = part index (0 background; names in dataset.json \"parts\"), grey",
    "gloss": "uint16 = round(gloss * 65535), grey",
}


def _png16(path: Path, layer: str, a: np.ndarray) -> None:
    import png

    if layer == "normal":
        v = (np.clip(a, -1, 1) + 1) * 0.5 * 65535
    elif layer in ("material", "part"):
        v = a
    elif layer == "depth":
        v = np.clip(a * 1000.0, 0, 65535)
    else:
        v = np.clip(a, 0, 1) * 65535
    v = np.round(v).astype(np.uint16)
    h, w, c = v.shape
    with atomic_target(path) as tmp, open(tmp, "wb") as fh:
        png.Writer(w, h, greyscale=c == 1, bitdepth=16).write(fh, v.reshape(h, w * c).tolist())


def convert_dataset(root: Path, out: Path, fmt: str, layers: list[str] | None = None, progress: bool = True) -> Path:
    """Write every sample of `root` as OUT/LAYER/NNNNNN.npy|png (checksums verified on reading),
    with OUT/manifest.jsonl (the rows) and OUT/conversion.json (source, format, layer encodings)."""
    if fmt not in FORMATS:
        raise DatasetError(f"--to {fmt!r}: expected one of {', '.join(FORMATS)}")
    ds = open_dataset(root)
    wanted = list(layers) if layers else list(ds.layers)
    unknown = [k for k in wanted if k not in ds.layers]
    if unknown:
        raise DatasetError(f"--layers {','.join(unknown)}: a {ds.kind} set has {', '.join(ds.layers)}")
    out = Path(out)
    if out.exists() and not folder_is_empty(out):
        raise DatasetError(f"--out {out}: exists and is not an empty folder; choose a new folder")
    with locked_folder(out):
        for k in wanted:
            (out / k).mkdir(parents=True, exist_ok=True)
        for i in tqdm(range(len(ds)), desc="convert", unit="sample", disable=not progress):
            arrays = ds.load(i, wanted)
            index = ds.rows[i]["index"]
            for k, a in arrays.items():
                path = out / k / f"{index:06d}.{'npy' if fmt == 'npy' else 'png'}"
                if fmt == "npy":
                    with atomic_target(path) as tmp, open(tmp, "wb") as fh:
                        np.save(fh, a.astype(np.float32))
                else:
                    _png16(path, k, a)
        with atomic_target(out / "manifest.jsonl") as tmp:
            Path(tmp).write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in ds.rows))
        atomic_write_json(out / "conversion.json", {  # written last: its presence says the conversion is whole
            "source": str(Path(root).resolve()), "source_identity": ds.identity(), "format": fmt, "layers": wanted,
            "count": len(ds), "encoding": ({k: PNG16_ENCODING[k] for k in wanted} if fmt == "png16" else
                                           {k: "float32 (H, W, C), the dataset's units" for k in wanted})})
    return out
