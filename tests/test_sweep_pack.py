"""The objective sweep's packs (bench/objective_sweep.py): what travels to a GPU machine decodes back."""
import sys
from pathlib import Path

import numpy as np

from .conftest import bench_module

_sweep = bench_module("objective_sweep")
jpeg_decode, jpeg_encode, load_packed, unpack = _sweep.jpeg_decode, _sweep.jpeg_encode, _sweep.load_packed, _sweep.unpack


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


def _synthetic_pack(path: Path) -> None:
    """A protocol pack of random maps at 32x64, with the sources a real pack records."""
    import json

    rng = np.random.default_rng(1)
    u8 = lambda *shape: rng.integers(0, 256, shape).astype(np.uint8)  # noqa: E731
    sources = {k: {"path": f"/data/{k}", "identity": {"kind": k, "count": 8, "manifest_sha256": "0" * 64}}
               for k in ("intrinsics", "real", "probe")}
    np.savez_compressed(path, MS=u8(8, 9, 32, 64), XR=u8(4, 3, 32, 64), YR=u8(4, 9, 32, 64), PX=u8(2, 3, 32, 64),
                        PY=u8(2, 9, 32, 64), PM=(u8(2, 1, 32, 64) > 100).astype(np.uint8) * 255,
                        setting="protocol", sources=json.dumps(sources))


def test_a_sweep_run_stopped_and_resumed_from_its_run_folder_matches_one_run_through(tmp_path, monkeypatch):
    """`run --run-dir` checkpoints as `iae-train fit` does and resumes bit for bit (weights,
    optimisers, schedules, EMA, the batch sampler), so a GPU lease can train in parts; the folder
    records the pack's source sets for `iae-eval report`."""
    import json

    import torch

    from objective_sweep import main
    from train.inference import load_run_checkpoint

    _synthetic_pack(tmp_path / "p.npz")
    threads = torch.get_num_threads()

    def run(name: str, *extra: str) -> None:
        monkeypatch.setattr(sys, "argv", [
            "objective_sweep.py", "run", "--data", str(tmp_path / "p.npz"), "--steps", "6", "--every", "2", "--batch", "2",
            "--device", "cpu", "--threads", str(threads), "--out", str(tmp_path / f"{name}.jsonl"),
            "--run-dir", str(tmp_path / name), "--set", "model.r_ngf=8", "--set", "model.h_ngf=8",
            "--set", "model.d_ndf=8", *extra])
        main()

    run("through")
    run("parts", "--stop-at", "3")
    assert (tmp_path / "parts" / "checkpoints" / "step_00000003.safetensors").exists()
    run("parts", "--stop-at", "3")  # already there: nothing more
    assert not (tmp_path / "parts" / "checkpoints" / "step_00000004.safetensors").exists()
    run("parts")
    rows = {n: [json.loads(x) for x in (tmp_path / f"{n}.jsonl").read_text().splitlines()] for n in ("through", "parts")}
    assert [r["step"] for r in rows["parts"]] == [2, 3, 4, 6]
    strip = lambda r: {k: v for k, v in r.items() if k != "t"}  # noqa: E731
    assert strip(rows["parts"][-1]) == strip(rows["through"][-1])  # the same figures at step 6
    opts = json.loads((tmp_path / "parts" / "training_options.json").read_text())
    assert opts["intrinsics"] == "/data/intrinsics" and opts["data_identity"]["real"]["kind"] == "real"
    cfg, model, step = load_run_checkpoint(tmp_path / "parts")[:3]
    assert step == 6 and model.weights == "moving average"

    # slim (what leaves a GPU lease: the generators' EMA weights in float16) and back: the same H
    import tarfile

    runs = tmp_path / "runs"
    runs.mkdir()
    (tmp_path / "parts").rename(runs / "parts")
    monkeypatch.setattr(sys, "argv", ["objective_sweep.py", "slim", "--runs-dir", str(runs), "--out", str(tmp_path / "tars")])
    main()
    with tarfile.open(tmp_path / "tars" / "runs1.tar") as tar:
        tar.extractall(tmp_path / "back", filter="data")
    monkeypatch.setattr(sys, "argv", ["objective_sweep.py", "unslim", "--slim", str(tmp_path / "back"),
                                      "--runs-dir", str(tmp_path / "restored")])
    main()
    _, back, step = load_run_checkpoint(tmp_path / "restored" / "parts")[:3]
    x = torch.rand(1, 3, 32, 64) * 2 - 1
    with torch.no_grad():
        assert step == 6 and (back.decompose(x) - model.decompose(x)).abs().max() < 0.02  # float16 weights


def test_the_sweep_grid_says_where_each_run_stopped_and_a_rerun_goes_on(tmp_path):
    """What a GPU lease's log shows: each run's step of its schedule, and a refused setting as a
    failed run named with its one-line reason, not a traceback."""
    import subprocess

    _synthetic_pack(tmp_path / "p.npz")
    small = '"model.r_ngf=8", "model.h_ngf=8", "model.d_ndf=8"'
    (tmp_path / "v.toml").write_text(f'[tiny]\nset = [{small}]\n'
                                     f'[too_small]\nconfig = "paper"\nset = ["model.kind=oracle", {small}]\n')

    def grid(*extra: str) -> str:
        cmd = [sys.executable, str(Path(__file__).parents[1] / "bench" / "objective_sweep.py"), "grid",
               "--data", str(tmp_path / "p.npz"), "--variants", str(tmp_path / "v.toml"), "--seeds", "0",
               "--steps", "4", "--every", "2", "--batch", "2", "--device", "cpu", "--out", str(tmp_path / "o"),
               "--runs-dir", str(tmp_path / "runs"), *extra]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        return proc.stdout

    out = grid("--stop-at", "2")
    assert "tiny_s0: step 2 of 4, stopped; the same command with this --runs-dir goes on" in out
    assert "too_small_s0: step 0 of 4, failed" in out
    assert (tmp_path / "o" / "too_small_s0.err").read_text().strip() == (
        "run: data.height/width (32x64) must be at least 64 (the networks of model.kind = 'oracle' downsample by 32)")
    assert "tiny_s0: step 4 of 4, complete" in grid("--only", "tiny")
    assert "tiny_s0: step 4 of 4, complete" in grid("--only", "tiny")  # nothing left to train
