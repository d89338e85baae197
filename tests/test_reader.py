"""Reading sets from one's own code: the NumPy reader API, the torch Dataset wrapper and
`iae-gen convert` for tools without multi-layer EXR."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from blender_gen.dataset import DatasetError, open_dataset

from .conftest import ROOT
from .train_helpers import tiny_intrinsics


def test_samples_come_as_numpy_dicts_of_named_layers_with_checksums_verified(tmp_path):
    root = tiny_intrinsics(tmp_path / "pbr", n=3, kind="pbr")
    ds = open_dataset(root)
    assert ds.layers == ("rgb", "normal", "albedo", "reflection", "mask", "material")
    got = list(ds.samples(["rgb", "normal"]))
    assert [s["index"] for s in got] == [0, 1, 2] and got[0]["meta"]["car"]["name"] == "blob"
    assert got[0]["rgb"].shape == (32, 64, 3) and got[0]["rgb"].dtype == np.float32 and "albedo" not in got[0]
    data = (root / "samples" / "000001.exr").read_bytes()
    (root / "samples" / "000001.exr").write_bytes((root / "samples" / "000000.exr").read_bytes())
    with pytest.raises(DatasetError, match="000001.exr: checksum mismatch"):
        list(ds.samples())
    (root / "samples" / "000001.exr").write_bytes(data)
    import blender_gen.dataset as reader  # the reader API needs neither bpy nor torch

    assert "bpy" not in reader.__dict__ and "torch" not in reader.__dict__


def test_the_torch_dataset_wrapper_gives_tensors_in_either_space(tmp_path):
    from torch.utils.data import DataLoader

    from train.data import LayerDataset

    root = tiny_intrinsics(tmp_path / "pbr", n=4, kind="pbr")
    batch = next(iter(DataLoader(LayerDataset(root, ["rgb", "normal", "material"]), batch_size=2)))
    assert batch["rgb"].shape == (2, 3, 32, 64) and batch["index"].tolist() == [0, 1]
    assert batch["material"].max() == 19
    net = LayerDataset(root, ["albedo"], network=True)[0]["albedo"]
    assert net.min() >= -1 and net.max() <= 1 and torch.isclose(net.min(), torch.tensor(-1.0))
    with pytest.raises(DatasetError, match="no layer"):
        LayerDataset(tiny_intrinsics(tmp_path / "intr", n=1), ["rgb"])


@pytest.mark.parametrize("fmt", ["npy", "png16"])
def test_convert_writes_one_file_per_sample_and_layer(tmp_path, fmt):
    root = tiny_intrinsics(tmp_path / "pbr", n=2, kind="pbr")
    out = tmp_path / "conv"
    proc = subprocess.run([sys.executable, "-m", "blender_gen.cli", "convert", str(root), "--to", fmt, "--out", str(out),
                           "--layers", "normal,albedo,material", "--quiet"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    info = json.loads((out / "conversion.json").read_text())
    assert info["layers"] == ["normal", "albedo", "material"] and info["count"] == 2
    truth = open_dataset(root).load(1)
    if fmt == "npy":
        assert np.array_equal(np.load(out / "albedo" / "000001.npy"), truth["albedo"])
    else:
        import png

        w, h, rows, meta = png.Reader(filename=str(out / "normal" / "000001.png")).asDirect()
        assert meta["bitdepth"] == 16 and (w, h) == (64, 32)
        n = np.array(list(rows), dtype=np.float64).reshape(h, w, 3) / 65535 * 2 - 1
        assert np.abs(n - np.clip(truth["normal"], -1, 1)).max() < 1e-4
        _, _, rows, _ = png.Reader(filename=str(out / "material" / "000001.png")).asDirect()
        assert np.array(list(rows)).max() == 19
    again = subprocess.run([sys.executable, "-m", "blender_gen.cli", "convert", str(root), "--to", fmt, "--out", str(out)],
                           cwd=ROOT, capture_output=True, text=True)
    assert again.returncode == 1 and "not an empty folder" in again.stderr
