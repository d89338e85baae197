"""Issue 19.14: a sample file swapped for another valid EXR, or holding NaN, is named at once by
training and inference instead of being used silently (or stopping training as "non-finite loss")."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from blender_gen.dataset import read_exr, sha256_file, write_exr

from .conftest import ROOT
from .train_helpers import TINY, tiny_intrinsics, tiny_photos


def _train(*args):
    return subprocess.run([sys.executable, "-m", "train.cli", *args], cwd=ROOT, capture_output=True, text=True)


def _fit(run, intr, photos, steps="2"):
    return _train("fit", "--run-dir", str(run), "--config", "cpu-small", "--intrinsics", str(intr), "--real",
                  str(photos), "--max-steps", steps, "--quiet", "--set", "data.cache_gb=0", *TINY)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """One tiny run and its clean data, shared: each test corrupts a copy of the data."""
    base = tmp_path_factory.mktemp("bad_samples")
    intr, photos = tiny_intrinsics(base / "intr"), tiny_photos(base / "photos", n=6)
    run = base / "run"
    assert _fit(run, intr, photos).returncode == 0
    return run, intr, photos


def test_a_sample_replaced_by_another_valid_exr_is_refused(tmp_path, trained):
    run, clean, photos = trained
    intr = shutil.copytree(clean, tmp_path / "intr")
    shutil.copy(intr / "samples" / "000001.exr", intr / "samples" / "000000.exr")
    bad = _fit(tmp_path / "run2", intr, photos)
    assert bad.returncode == 1 and "Traceback" not in bad.stderr
    assert "000000.exr: checksum mismatch" in bad.stderr
    render = _train("render", "--run", str(run), "--intrinsics", str(intr), "--out", str(tmp_path / "r"), "--quiet")
    assert render.returncode == 1 and "000000.exr: checksum mismatch" in render.stderr


def test_nan_in_a_sample_names_the_sample(tmp_path, trained):
    run, clean, photos = trained
    intr = shutil.copytree(clean, tmp_path / "intr")
    path = intr / "samples" / "000002.exr"
    layers = read_exr(path)
    layers["normal"][5, 5] = np.nan
    write_exr(path, layers)
    rows = [json.loads(line) for line in (intr / "manifest.jsonl").read_text().splitlines()]
    for r in rows:
        if r["index"] == 2:
            r["sha256"] = sha256_file(path)  # a consistent manifest: the file itself is bad
    (intr / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    bad = _fit(tmp_path / "run2", intr, photos, steps="4")
    assert bad.returncode == 1 and "000002.exr: layer 'normal' holds NaN" in bad.stderr
    assert "non-finite loss" not in bad.stderr and "Traceback" not in bad.stderr
    render = _train("render", "--run", str(run), "--intrinsics", str(intr), "--out", str(tmp_path / "r"), "--quiet")
    assert render.returncode == 1 and "000002.exr: layer 'normal' holds NaN" in render.stderr


def test_decompose_skips_a_bomb_image_and_writes_the_others_whole(tmp_path, trained):
    """A decompression-bomb photo among good ones: named and skipped (exit 1 only with --strict), no
    traceback, and the other photos' predictions written as a complete set that records the skipped one."""
    from PIL import Image

    run, _, clean = trained
    photos = shutil.copytree(clean, tmp_path / "photos")
    big = Image.new("1", (14000, 14000))  # 196 MP: over twice Pillow's limit, a bomb
    big.save(photos / "zz_bomb.png", optimize=False, compress_level=1)
    out = tmp_path / "pred"
    bad = _train("decompose", "--run", str(run), "--images", str(photos), "--out", str(out), "--quiet", "--strict")
    assert bad.returncode == 1 and "zz_bomb.png" in bad.stderr and "Traceback" not in bad.stderr
    info = json.loads((out / "dataset.json").read_text())
    n = len(list(clean.iterdir()))
    assert info["complete"] and info["count"] == n and info["skipped"][0]["file"].endswith("zz_bomb.png")
    assert not list((out / "photos").glob("zz_bomb*"))


def test_training_skips_unreadable_photos_and_names_them(tmp_path, trained):
    """A photo folder with a file that is no image and a JPEG cut short: the training names both,
    uses the others and finishes (one corrupt photo among thousands must not stop a run)."""
    import io

    from PIL import Image

    run, intr, clean = trained
    photos = shutil.copytree(clean, tmp_path / "photos")
    (photos / "not_a_photo.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    buf = io.BytesIO()
    noise = np.random.default_rng(0).integers(0, 256, (200, 300, 3), dtype=np.uint8)
    Image.fromarray(noise).save(buf, "JPEG")  # its header reads, its pixels end half-way
    (photos / "cut_short.jpg").write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    res = _train("fit", "--run-dir", str(tmp_path / "run"), "--config", "cpu-small", "--intrinsics", str(intr),
                 "--real", str(photos), "--max-steps", "2", "--quiet", *TINY)  # the cache reads every photo
    assert res.returncode == 0, res.stderr
    assert "--real: skipped 1 photo(s) that could not be read" in res.stderr and "not_a_photo.jpg" in res.stderr
    assert f"using the other {len(list(clean.iterdir())) + 1}" in res.stderr
    assert "cut_short.jpg: cannot read image" in res.stderr and "another photo takes its place" in res.stderr
    assert "Traceback" not in res.stderr
