"""`iae-train export`: ONNX / TorchScript files that reproduce PyTorch and refuse what is not theirs."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from train.export import ExportedNet, ExportError, check_export, example_input, export_network, read_metadata
from train.inference import load_run

from .test_train import _run
from .train_helpers import TINY, tiny_intrinsics, tiny_photos


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two tiny trained runs (the second with other weights: another seed)."""
    root = tmp_path_factory.mktemp("export")
    intr, photos = tiny_intrinsics(root / "intr"), tiny_photos(root / "photos")
    out = []
    for name, seed in (("a", 0), ("b", 1)):
        run = root / name
        _run("fit", "--config", "cpu-small", "--intrinsics", str(intr), "--real", str(photos), "--run-dir", str(run),
             "--max-steps", "3", "--quiet", *TINY, "--set", f"run.seed={seed}")
        out.append(run)
    return out


@pytest.mark.parametrize("net, fmt", [("R", "onnx"), ("H", "onnx"), ("R", "torchscript"), ("H", "torchscript")])
def test_export_reproduces_pytorch_at_any_batch_size(runs, tmp_path, net, fmt):
    run = runs[0]
    path = tmp_path / f"{net}.{'onnx' if fmt == 'onnx' else 'pt'}"
    export_network(run, net, fmt, path, resolution=(96, 48))
    meta = read_metadata(path)
    assert (meta["net"], meta["format"], meta["width"], meta["height"]) == (net, fmt, 96, 48)
    assert "sRGB" in meta["input_doc" if net == "H" else "output_doc"] and meta["step"] == 3
    _, model, _ = load_run(run)
    exported = ExportedNet(path)
    for batch in (1, 3):  # the batch axis is dynamic
        x = example_input(net, batch, 48, 96, seed=batch)
        with torch.no_grad():
            ref = (model.render if net == "R" else model.decompose)(torch.from_numpy(x)).numpy()
        got = exported(x)
        assert got.shape == ref.shape == (batch, 3 if net == "R" else 9, 48, 96)
        np.testing.assert_allclose(got, ref, atol=1e-4)  # the tolerance check_export states
    assert check_export(path, run)["ok"]


def test_half_onnx_runs_on_onnx_runtime_within_its_tolerance(runs, tmp_path):
    path = tmp_path / "R16.onnx"
    export_network(runs[0], "R", "onnx", path, half=True)
    result = check_export(path, runs[0])
    assert read_metadata(path)["dtype"] == "float16" and result["ok"] and result["max_abs_diff"] > 0


def test_a_file_of_another_run_or_a_corrupt_file_is_refused(runs, tmp_path):
    a, b = runs
    path = tmp_path / "R.onnx"
    export_network(a, "R", "onnx", path)
    with pytest.raises(ExportError, match=r"exported from .*, not from the newest checkpoint of --run"):
        check_export(path, b)
    torn = tmp_path / "torn.onnx"
    torn.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ExportError, match=r"torn.onnx: not a readable onnx file"):
        read_metadata(torn)
    ts = tmp_path / "R.pt"
    export_network(a, "R", "torchscript", ts)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a zip" + ts.read_bytes()[100:])
    with pytest.raises(ExportError, match=r"bad.pt: not a readable torchscript file"):
        ExportedNet(bad)
    plain = tmp_path / "plain.pt"  # TorchScript, but not this project's export
    torch.jit.save(torch.jit.script(torch.nn.Identity()), str(plain))
    with pytest.raises(ExportError, match="without this project's export metadata"):
        read_metadata(plain)


def test_export_command_checks_the_file_and_errors_name_the_option(runs, tmp_path):
    out = tmp_path / "H.onnx"
    proc = _run("export", "--run", str(runs[0]), "--net", "H", "--out", str(out))
    assert "tolerance" in proc.stdout and ": ok" in proc.stdout and out.exists()
    assert not list(tmp_path.glob("*.tmp*"))  # written under a temporary name, then renamed
    bad = _run("export", "--run", str(runs[0]), "--net", "R", "--out", str(tmp_path / "x.onnx"),
               "--resolution", "98x48", check=False)
    assert bad.returncode == 1 and "--resolution 98x48: width and height must be multiples of" in bad.stderr
    assert not (tmp_path / "x.onnx").exists()
    bad = _run("check-export", str(out), "--run", str(runs[1]), check=False)
    assert bad.returncode == 1 and "export it again" in bad.stderr and "Traceback" not in bad.stderr
    meta = json.loads(json.dumps(read_metadata(out)))
    assert meta["checkpoint"] == "step_00000003.safetensors" and len(meta["checkpoint_sha256"]) == 64


def test_export_never_replaces_a_file_unasked_nor_writes_inside_a_run(runs, tmp_path):
    """Issue 19.4: an existing --out needs --force; a run folder is never written (its newest
    checkpoint once became a TorchScript zip); --resolution is bounded before anything is allocated."""
    newest = sorted((runs[0] / "checkpoints").glob("step_*.safetensors"))[-1]
    before = newest.read_bytes()
    bad = _run("export", "--run", str(runs[0]), "--net", "R", "--format", "torchscript", "--out", str(newest),
               "--force", check=False)
    assert bad.returncode == 1 and "inside the run folder" in bad.stderr and "Traceback" not in bad.stderr
    assert newest.read_bytes() == before
    out = tmp_path / "R.onnx"
    out.write_bytes(b"mine")
    bad = _run("export", "--run", str(runs[0]), "--net", "R", "--out", str(out), "--no-check", check=False)
    assert bad.returncode == 1 and "exists; choose a new file or pass --force" in bad.stderr
    assert out.read_bytes() == b"mine"
    _run("export", "--run", str(runs[0]), "--net", "R", "--out", str(out), "--no-check", "--force")
    assert out.read_bytes() != b"mine"
    huge = _run("export", "--run", str(runs[0]), "--net", "R", "--out", str(tmp_path / "h.onnx"),
                "--resolution", "100000x100000", check=False)
    assert huge.returncode == 1 and "at most" in huge.stderr and "Traceback" not in huge.stderr


def test_a_video_is_not_written_over_an_existing_file_or_into_a_run(runs, tmp_path):
    intr = tiny_intrinsics(tmp_path / "intr", n=2)
    video = tmp_path / "r.gif"
    video.write_bytes(b"keep")
    bad = _run("render", "--run", str(runs[0]), "--intrinsics", str(intr), "--out", str(tmp_path / "f1"),
               "--video", str(video), "--quiet", check=False)
    assert bad.returncode == 1 and "--video" in bad.stderr and "pass --force" in bad.stderr
    assert video.read_bytes() == b"keep" and not (tmp_path / "f1").exists()
    inside = _run("render", "--run", str(runs[0]), "--intrinsics", str(intr), "--out", str(tmp_path / "f2"),
                  "--video", str(runs[0] / "r.gif"), "--force", "--quiet", check=False)
    assert inside.returncode == 1 and "inside the run folder" in inside.stderr
    _run("render", "--run", str(runs[0]), "--intrinsics", str(intr), "--out", str(tmp_path / "f3"),
         "--video", str(video), "--force", "--quiet")
    assert video.read_bytes()[:3] == b"GIF"


def test_a_nan_frame_rate_is_refused_before_rendering(runs, tmp_path):
    intr = tiny_intrinsics(tmp_path / "intr", n=2)
    bad = _run("render", "--run", str(runs[0]), "--intrinsics", str(intr), "--out", str(tmp_path / "f"),
               "--video", str(tmp_path / "v.gif"), "--fps", "nan", "--quiet", check=False)
    assert bad.returncode == 2 and "--fps" in bad.stderr and not (tmp_path / "f").exists()


def test_edited_metadata_is_a_one_line_error(runs, tmp_path):
    """Issue 19.10: height as a string or huge, `net` missing or changed, metadata as a JSON list."""
    import onnx

    from train.export import EXTRA_FILE

    src = tmp_path / "R.onnx"
    _run("export", "--run", str(runs[0]), "--net", "R", "--out", str(src), "--no-check")

    def edited(name, change):
        proto = onnx.load(str(src))
        meta = {p.key: json.loads(p.value) for p in proto.metadata_props}
        change(meta)
        del proto.metadata_props[:]
        for k, v in meta.items():
            proto.metadata_props.add(key=k, value=json.dumps(v))
        onnx.save(proto, str(tmp_path / name))
        return tmp_path / name

    cases = {
        "string.onnx": (lambda m: m.update(height="32"), "'height'"),
        "huge.onnx": (lambda m: m.update(height=10**6, width=10**6), "at most"),
        "nonet.onnx": (lambda m: m.pop("net"), "'net'"),
        "swapped.onnx": (lambda m: m.update(net="H"), "metadata"),
    }
    from train.export import ExportError, check_export, export_network

    for k, (name, (change, message)) in enumerate(cases.items()):
        path = edited(name, change)
        if k == 0:  # the command: one line, exit 1
            proc = _run("check-export", str(path), "--run", str(runs[0]), check=False)
            assert proc.returncode == 1 and message in proc.stderr and "Traceback" not in proc.stderr, (name, proc.stderr)
        with pytest.raises(ExportError, match=message):  # the rest in-process: the same error, no subprocess each
            check_export(path, runs[0])
    ts = tmp_path / "R.pt"
    export_network(runs[0], "R", "torchscript", ts)
    module = torch.jit.load(str(ts))
    torch.jit.save(module, str(tmp_path / "list.pt"), _extra_files={EXTRA_FILE: json.dumps([1, 2])})
    with pytest.raises(ExportError, match="without this project's export metadata"):
        check_export(tmp_path / "list.pt", runs[0])
