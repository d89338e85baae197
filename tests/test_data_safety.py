"""Data safety: manifests cannot point outside their dataset, one writer per folder, workers
die with their parent, and failed writes leave nothing half-written."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from blender_gen.dataset import (DatasetError, DatasetWriteError, atomic_write_bytes, locked_folder, open_dataset,
                                 read_manifest, save_png, temp_name, write_exr)
from tests.conftest import ROOT, run_gen
from tests.train_helpers import tiny_intrinsics


def _rows(root: Path) -> list[dict]:
    return [json.loads(line) for line in (root / "manifest.jsonl").read_text().splitlines()]


def _write_rows(root: Path, rows: list[dict]) -> None:
    (root / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def _one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode != 0, proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr
    for n in needles:
        assert n in proc.stderr, proc.stderr


def test_merge_refuses_a_manifest_that_names_a_file_outside_its_folder(tmp_path):
    shard = tiny_intrinsics(tmp_path / "shard", n=2)
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours")
    rows = _rows(shard)
    # a row that passes the old checks: the file exists and its checksum matches
    rows.append({**rows[0], "index": 7, "file": "../victim.txt", "sha256": __import__("hashlib").sha256(
        victim.read_bytes()).hexdigest()})
    _write_rows(shard, rows)
    out = tmp_path / "deep" / "merged"
    proc = run_gen("merge", "--out", str(out), str(shard), "--quiet", check=False)
    _one_line_error(proc, "'file' must be 'samples/000007.exr'", "corrupt")
    assert not (tmp_path / "deep" / "victim.txt").exists()
    assert not (out / "manifest.jsonl").exists()
    assert victim.read_text() == "not yours"


@pytest.mark.parametrize("bad", [
    {"file": "/etc/passwd"},
    {"file": "../other/samples/000001.exr"},
    {"file": "samples/000001.exr"},  # another sample's file
    {"sha256": None},
    {"index": -1},
    {"index": "0"},
])
def test_readers_refuse_rows_that_do_not_name_their_own_sample(tmp_path, bad):
    root = tiny_intrinsics(tmp_path / "ds", n=2)
    rows = _rows(root)
    row = {**rows[0], **bad}
    if bad.get("sha256", 1) is None:
        del row["sha256"]
    _write_rows(root, [row, rows[1]])
    with pytest.raises(DatasetError, match="line 1: .*corrupt"):
        open_dataset(root)
    proc = run_gen("inspect", str(root), "--quiet", check=False)
    _one_line_error(proc, "corrupt")
    assert "complete" not in proc.stdout


def test_duplicate_rows_count_once(tmp_path):
    root = tiny_intrinsics(tmp_path / "ds", n=3)
    rows = _rows(root)
    _write_rows(root, rows + rows[:2])
    assert [r["index"] for r in read_manifest(root / "manifest.jsonl")] == [2, 0, 1]
    assert len(open_dataset(root)) == 3


def test_a_second_writer_on_the_same_folder_fails_naming_the_holder(tmp_path):
    out = tmp_path / "intr"
    with locked_folder(out):
        proc = run_gen("intrinsics", "--out", str(out), "--count", "2", "--resolution", "64x32", "--quiet", check=False)
        merged = run_gen("merge", "--out", str(out), str(tmp_path), "--quiet", check=False)
    _one_line_error(proc, f"is being written by pid {os.getpid()}")
    _one_line_error(merged, "is being written by pid")
    assert sorted(p.name for p in out.iterdir()) == [".lock"]


def test_an_incomplete_merge_exits_nonzero(tmp_path):
    root = tiny_intrinsics(tmp_path / "ds", n=3)
    info = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**info, "count_requested": 5}))
    proc = run_gen("merge", "--out", str(tmp_path / "m"), str(root), "--quiet", check=False)
    _one_line_error(proc, "INCOMPLETE", "2 sample(s) missing")
    assert len(open_dataset(tmp_path / "m")) == 3


@pytest.mark.parametrize("args, message", [
    (["--count", "-1"], "Invalid value for '--count'"),
    (["--count", "1000000000"], "Invalid value for '--count'"),
    (["--count", "2", "--workers", "0"], "Invalid value for '--workers'"),
    (["--count", "2", "--workers", "many"], "expected a number of processes from 1 to 256, or auto"),
    (["--count", "2", "--samples", "0"], "Invalid value for '--samples'"),
])
def test_ranges_are_checked_where_options_are_declared(tmp_path, args, message):
    proc = run_gen("intrinsics", "--out", str(tmp_path / "x"), *args, check=False)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (tmp_path / "x").exists()


def _children(pid: int) -> set[int]:
    kids = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            kids.update(int(k) for k in (task / "children").read_text().split())
        except OSError:
            continue
    return kids


def _descendants(pid: int) -> set[int]:
    out, todo = set(), [pid]
    while todo:
        kids = _children(todo.pop())
        out.update(kids)
        todo += kids
    return out


def _is_worker(pid: int) -> bool:
    try:
        return b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.blender
def test_workers_die_with_their_parent(tmp_path):
    out = tmp_path / "intr"
    proc = subprocess.Popen([sys.executable, "-m", "blender_gen.cli", "intrinsics", "--out", str(out), "--count", "400",
                             "--resolution", "64x32", "--workers", "2", "--quiet"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline:
            manifest = out / "manifest.jsonl"
            if manifest.exists() and len(manifest.read_text().splitlines()) >= 2:
                break
            time.sleep(0.2)
        # the pool's processes are the generator's own children; a process a worker forks shows the
        # worker's command line until it execs, so deeper descendants are not counted as workers
        workers = {p for p in _children(proc.pid) if _is_worker(p)}
        assert len(workers) == 2, "the two Blender workers should be running"
        workers |= {p for p in _descendants(proc.pid) if _is_worker(p)}  # and whatever they started must die too
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 10
        while time.time() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.1)
        assert not any(_alive(p) for p in workers), "workers outlived their killed parent"
    finally:
        if proc.poll() is None:
            proc.kill()
    # the killed run resumes: the lock died with it and the finished samples are kept
    assert len(read_manifest(out / "manifest.jsonl")) >= 2


def _full_path(tmp_path: Path, name: str) -> Path:
    """A target whose temporary is a link to /dev/full: every write fails with ENOSPC."""
    target = tmp_path / name
    os.symlink("/dev/full", temp_name(target))
    return target


@pytest.mark.parametrize("writer", [
    lambda p: atomic_write_bytes(p, b"x" * 100_000),
    lambda p: write_exr(p, {"mask": __import__("numpy").ones((64, 64, 1))}),
    lambda p: save_png(p, __import__("numpy").zeros((64, 64, 3), "uint8")),
])
def test_a_full_disk_is_one_error_naming_the_file_and_leaves_nothing(tmp_path, writer):
    target = _full_path(tmp_path, "file.out")
    with pytest.raises(DatasetWriteError) as err:
        writer(target)
    assert str(err.value).startswith(f"cannot write {target}: ")
    # the OS's reason follows (OpenEXR, which seeks, sees /dev/full as "Invalid argument")
    assert len(str(err.value).splitlines()) == 1 and str(err.value).split(": ", 1)[1]
    assert list(tmp_path.iterdir()) == [], "neither the file nor its temporary may remain"


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 600 KiB file system, to fill up for real (needs root, as in CI)."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


@pytest.mark.blender
def test_generation_on_a_full_then_read_only_disk(small_tmpfs):
    out = small_tmpfs / "intr"
    proc = run_gen("intrinsics", "--out", str(out), "--count", "400", "--resolution", "128x64", "--quiet", check=False)
    _one_line_error(proc, "No space left on device")
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    leftovers = [p for p in out.rglob(".*") if p.name != ".lock"]
    assert leftovers == [], f"half-written temporaries left: {leftovers}"
    ds = open_dataset(out)
    assert 0 < len(ds) < 400
    for row in ds.rows:  # every sample the manifest names is whole
        assert (out / row["file"]).stat().st_size > 0
    subprocess.run(["mount", "-o", "remount,ro", str(small_tmpfs)], check=True)
    proc = run_gen("intrinsics", "--out", str(out), "--count", "400", "--resolution", "128x64", "--quiet", check=False)
    _one_line_error(proc, "Read-only file system", str(out))


# ------------------------------------------------------------------ remaining one-line errors

@pytest.mark.blender
def test_a_blend_that_is_not_a_blend_and_rules_that_are_not_utf8(tmp_path):
    rules = ROOT / "data_manifests" / "kenney_car_kit_rules.toml"
    fake = tmp_path / "car.blend"
    fake.write_bytes(b"PK\x03\x04 a zip file, not Blender's")
    proc = run_gen("intrinsics", "--out", str(tmp_path / "o"), "--count", "1", "--resolution", "64x32", "--cars",
                   str(fake), "--car-rules", str(rules), "--quiet", check=False)
    _one_line_error(proc, "not a .blend file")
    latin = tmp_path / "rules.toml"
    latin.write_bytes("# r\xe9gles\n[model]\n".encode("latin-1"))
    proc = run_gen("intrinsics", "--out", str(tmp_path / "p"), "--count", "1", "--cars", str(fake), "--car-rules",
                   str(latin), check=False)
    _one_line_error(proc, "not UTF-8 text")


def test_a_config_that_is_not_utf8_and_inception_that_is_not_torchscript(tmp_path):
    from train.config import ConfigError, load_config

    cfg = tmp_path / "mine.toml"
    cfg.write_bytes("# d\xe9faut\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="not UTF-8 text"):
        load_config(str(cfg))
    bogus = tmp_path / "inception.pt"
    bogus.write_bytes(b"\x80\x04 a pickle, not TorchScript")
    photos = tmp_path / "photos"
    from tests.train_helpers import tiny_photos

    tiny_photos(photos)
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "fid", "--real", str(photos), "--fake", str(photos),
                           "--inception", str(bogus)], cwd=ROOT, capture_output=True, text=True)
    _one_line_error(proc, "not a TorchScript file")


def test_inspect_on_a_predictions_dataset_and_on_a_row_without_checksum(tmp_path):
    root = tiny_intrinsics(tmp_path / "pred", n=2)
    info = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**info, "kind": "predictions"}))
    rows = [{k: v for k, v in r.items() if k in ("index", "file", "sha256")} for r in _rows(root)]
    _write_rows(root, rows)
    proc = run_gen("inspect", str(root), "--quiet", check=False)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    _write_rows(root, [{k: v for k, v in rows[0].items() if k != "sha256"}])
    _one_line_error(run_gen("inspect", str(root), "--quiet", check=False), "'sha256' must be 64 lowercase hex")


def test_negative_seeds_and_non_finite_numbers_are_refused_where_they_are_given(tmp_path):
    from click.testing import CliRunner

    from blender_gen.cli import main as gen_main
    from eval.cli import main as eval_main
    from train.config import ConfigError, load_config

    out = str(tmp_path / "d")
    for args, where in ((["intrinsics", "--out", out, "--count", "1", "--seed", "-1"], "--seed"),
                        (["label-parts", "x.glb", "--out", out, "--length", "nan"], "finite"),
                        (["turntable", "--out", out, "--radius", "nan"], "finite")):
        res = CliRunner().invoke(gen_main, args)
        assert res.exit_code == 2 and where in res.output, res.output
    for args in (["reproduce", "--seed", "-3", "--dry-run"], ["reproduce", "--run-seed", "-1", "--dry-run"],
                 ["reproduce", "--budget", "sanity", "--seeds", "0,-1", "--dry-run"]):
        res = CliRunner().invoke(eval_main, args)
        assert res.exit_code == 2 and "seed" in res.output, res.output
    for setting, message in (("run.seed=-1", "run.seed"), ("loss.w_ren=nan", "loss.w_ren"),
                             ("loss.w_dec=inf", "loss.w_dec"), ("data.cache_gb=nan", "data.cache_gb")):
        with pytest.raises(ConfigError, match=message):
            load_config("cpu-small", [setting])


def test_merge_refuses_a_shard_being_written_or_stopped_early_and_leaves_no_out(tmp_path):
    shard = tiny_intrinsics(tmp_path / "shard", n=2)
    with locked_folder(shard):
        proc = run_gen("merge", "--out", str(tmp_path / "m"), str(shard), "--quiet", check=False)
    _one_line_error(proc, "is being written by pid")
    info = json.loads((shard / "dataset.json").read_text())
    (shard / "dataset.json").write_text(json.dumps({**info, "complete": False}))
    proc = run_gen("merge", "--out", str(tmp_path / "m"), str(shard), "--quiet", check=False)
    _one_line_error(proc, "is incomplete")
    assert [p.name for p in (tmp_path / "m").iterdir()] == [".lock"]  # nothing that would refuse the rerun
    (shard / "dataset.json").write_text(json.dumps(info))
    run_gen("merge", "--out", str(tmp_path / "m"), str(shard), "--quiet")
    assert len(open_dataset(tmp_path / "m")) == 2


def test_label_parts_refuses_parallel_axes_and_models_reading_outside_their_folder(tmp_path):
    (tmp_path / "secret.bin").write_bytes(b"\0" * 12)
    car = tmp_path / "models" / "car.gltf"
    car.parent.mkdir()
    car.write_text('{"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.bin", "byteLength": 12}]}')
    proc = run_gen("label-parts", str(car), "--out", str(tmp_path / "r.toml"), check=False)
    _one_line_error(proc, "outside the model's folder")
    proc = run_gen("intrinsics", "--out", str(tmp_path / "d"), "--count", "1", "--resolution", "64x32", "--cars",
                   str(car), "--car-rules", "auto", "--quiet", check=False)
    _one_line_error(proc, "outside the model's folder")
    proc = run_gen("label-parts", str(car), "--out", str(tmp_path / "r.toml"), "--forward", "+Z", "--up", "-Z",
                   check=False)
    _one_line_error(proc, "the two axes must differ")
    assert not (tmp_path / "r.toml").exists()


def test_degenerate_models_and_malformed_results_are_one_line_errors(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "same.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
    for name in ("tri", "same"):
        proc = run_gen("label-parts", str(tmp_path / f"{name}.obj"), "--out", str(tmp_path / f"{name}.toml"),
                       check=False)
        _one_line_error(proc, f"{name}.obj", "too few or degenerate to be a car")
        assert not (tmp_path / f"{name}.toml").exists()
    (tmp_path / "results.json").write_text("[1, 2]")
    for args in (["seeds", str(tmp_path / "results.json")],
                 ["merge", str(tmp_path / "results.json"), "--out", str(tmp_path / "j.json")]):
        proc = subprocess.run([sys.executable, "-m", "eval.cli", *args], cwd=ROOT, capture_output=True, text=True)
        _one_line_error(proc, "not a report's results.json")


def test_one_line_errors_do_not_repeat_clicks_error_prefix():
    from blender_gen.cli_errors import first_line

    assert first_line(ValueError("Error: cannot read x.exr\nmore")) == "cannot read x.exr"
    assert first_line(ValueError("error:  Error: bad")) == "bad"
    assert first_line(ValueError("Error:")) == "ValueError"
    assert first_line(ValueError("no error: here")) == "no error: here"


def test_a_message_about_an_options_file_names_the_option(tmp_path):
    """The libraries know a path, the command line knows which option gave it: "--run PATH: ...".
    A path given as an argument, or a message that already names its option, stays as it is."""
    import click
    from click.testing import CliRunner

    from blender_gen.cli_errors import one_line_errors

    @click.command()
    @click.argument("folder")
    @click.option("--run")
    @click.option("--images", multiple=True)
    @click.option("--message")
    def cmd(folder, run, images, message):
        with one_line_errors():
            raise ValueError(message)

    def err(*args: str) -> str:
        res = CliRunner().invoke(cmd, list(args))
        assert res.exit_code == 1
        return res.output.strip().splitlines()[-1]

    run, other = str(tmp_path / "run"), str(tmp_path / "b")
    assert err("x", "--run", run, "--message", f"{run}: not a run folder") == f"Error: --run {run}: not a run folder"
    assert err("x", "--images", "a", "--images", other, "--message", f"{other}: unreadable") == \
        f"Error: --images {other}: unreadable"
    assert err(run, "--message", f"{run}: no such dataset directory") == f"Error: {run}: no such dataset directory"
    assert err("x", "--run", run, "--message", f"--run {run}: refused") == f"Error: --run {run}: refused"
    assert err("x", "--run", run, "--message", f"{run}x: other") == f"Error: {run}x: other"
