"""The objective sweep's packs (bench/objective_sweep.py): what travels to a GPU machine decodes back."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from objective_sweep import jpeg_decode, jpeg_encode, load_packed, unpack  # noqa: E402


def test_jpeg_packs_keep_every_map_and_their_order(tmp_path):
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:32, 0:64] / 64.0
    smooth = np.stack([np.sin(3 * x + k) * 0.5 + 0.5 for k in range(9)])  # smooth maps, like normals and albedo
    a = np.stack([np.roll(smooth, 7 * i, axis=-1) for i in range(3)])
    a = np.round(a * 255).astype(np.uint8)  # (3 samples, 9 channels, 32, 64)
    buf, off = jpeg_encode(a, quality=90)
    assert len(off) == 3 * 3 and buf.nbytes < a.nbytes / 4
    back = jpeg_decode(buf, off, np.array(a.shape))
    assert back.shape == a.shape
    err = np.abs(back.astype(int) - a.astype(int))
    assert err.mean() < 2.0  # a few 8-bit levels on smooth maps (4:4:4, no chroma subsampling)
    np.savez_compressed(tmp_path / "p.npz", MS__jpg=buf, MS__off=off, MS__shape=np.array(a.shape),
                        PM=rng.integers(0, 2, (3, 1, 32, 64)).astype(np.uint8) * 255)
    z = np.load(tmp_path / "p.npz")  # no pickle: every array is numeric
    assert np.array_equal(load_packed(z, "MS"), back)
    assert unpack(load_packed(z, "PM"), mask=True).max() == 1.0
