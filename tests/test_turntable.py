"""`iae-gen turntable`, R's video of it (`iae-train render --video`) and `iae-eval flicker`."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from blender_gen.dataset import open_dataset
from eval.flicker import frame_differences, temporal_error

from .conftest import ROOT, invoke_here, run_gen
from .test_train import _run as run_train
from .train_helpers import tiny_fit, tiny_intrinsics, tiny_photos

FRAMES = 6


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    root = tmp_path_factory.mktemp("turntable")
    common = ["--car", "sedan_a", "--frames", str(FRAMES), "--resolution", "64x32", "--radius", "7", "--height", "2",
              "--paint", "royal_blue", "--seed", "4", "--quiet"]
    run_gen("turntable", "--out", str(root / "intr"), *common)
    run_gen("turntable", "--out", str(root / "pbr"), *common, "--pbr", "--samples", "2")
    return root


@pytest.mark.blender
def test_frames_orbit_one_car_in_order_with_everything_else_fixed(paths):
    rows = open_dataset(paths / "intr").rows
    assert [r["index"] for r in rows] == list(range(FRAMES))
    assert {r["car"]["name"] for r in rows} == {"sedan_a"} and {r["paint"] for r in rows} == {"royal_blue"}
    assert len({json.dumps(r["envmap"]) for r in rows}) == 1 and len({r["seed"] for r in rows}) == 1
    target = np.array(rows[0]["camera"]["target"])
    for k, r in enumerate(rows):
        loc = np.array(r["camera"]["location"])
        assert math.hypot(*(loc - target)[:2]) == pytest.approx(7.0, abs=1e-6) and loc[2] == pytest.approx(2.0)
        angle = math.degrees(math.atan2(loc[1] - target[1], loc[0] - target[0])) % 360
        assert angle == pytest.approx(360 * k / FRAMES, abs=1e-6) or (k == 0 and angle == pytest.approx(360.0))
        assert r["camera"]["target"] == rows[0]["camera"]["target"]
        assert r["camera"]["focal_length"] == rows[0]["camera"]["focal_length"]  # fitted once, for all frames
    pbr = open_dataset(paths / "pbr")
    assert pbr.kind == "pbr" and [r["camera"] for r in pbr.rows] == [r["camera"] for r in rows]
    a, b = open_dataset(paths / "intr").load(2, ["normal", "mask"]), pbr.load(2, ["normal", "mask"])
    inner = (a["mask"][..., 0] == 1) & (b["mask"][..., 0] == 1)  # edges differ: PBR averages jittered samples
    assert inner.sum() > 50 and np.median(np.sum(a["normal"][inner] * b["normal"][inner], axis=-1)) > 0.99


@pytest.mark.blender
def test_bad_turntable_options_are_one_line_errors(tmp_path):
    bad = run_gen("turntable", "--out", str(tmp_path / "a"), "--car", "sedan_a", "--frames", "3",
                  "--paint", "mauve", "--quiet", check=False)
    assert bad.returncode and "--paint 'mauve': no such paint; expected one of" in bad.stderr
    bad = run_gen("turntable", "--out", str(tmp_path / "b"), "--car", "sedan", "--frames", "3", "--quiet", check=False)
    assert bad.returncode and "selects" in bad.stderr and "name one" in bad.stderr
    bad = run_gen("turntable", "--out", str(tmp_path / "d"), "--car", "nocar", "--frames", "3", "--quiet", check=False)
    assert bad.returncode and "--car: 'nocar' is neither a catalogue model" in bad.stderr  # the option it was given
    bad = run_gen("turntable", "--out", str(tmp_path / "c"), "--car", "sedan_a", "--frames", "3", "--radius", "2.5",
                  "--focal", "80", "--resolution", "64x32", "--quiet", check=False)
    assert bad.returncode and "does not fit" in bad.stderr and "--radius 2.5" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_the_fitted_focal_length_is_the_longest_that_shows_the_car_in_every_frame():
    from dataclasses import replace

    from blender_gen.camera import CameraError, CameraRanges, Orbit, _orbit_view, orbit_focal

    box = np.array([[x, y, z] for x in (-2.3, 2.3) for y in (-0.9, 0.9) for z in (0.0, 1.5)])
    orbit = Orbit(frames=12, radius=6.0, height=1.6)
    f = orbit_focal(box, orbit, 128, 64)
    ok = lambda focal: all(_orbit_view(box, replace(orbit, focal=focal), k, 128, 64, CameraRanges())[1]  # noqa: E731
                           for k in range(12))
    assert 10 <= f < 80 and ok(f) and not ok(f + 1)
    for radius, height in ((4.0, 0.5), (6.0, 3.0), (9.0, 1.0), (30.0, 2.0)):  # bisection = the longest that fits
        o = replace(orbit, radius=radius, height=height)
        fits = lambda focal, o=o: all(_orbit_view(box, replace(o, focal=float(focal)), k, 128, 64, CameraRanges())[1]  # noqa: E731
                                      for k in range(12))
        assert orbit_focal(box, o, 128, 64) == max(fl for fl in range(10, 81) if fits(fl)), (radius, height)
    assert orbit_focal(box, replace(orbit, focal=50.0), 128, 64) == 50.0  # a given focal length is kept
    with pytest.raises(CameraError, match="even with a 10 mm lens; increase --radius"):
        orbit_focal(box, replace(orbit, radius=2.4), 128, 64)


def test_frame_differences_on_hand_computed_frames():
    frames = np.zeros((3, 2, 2, 3))
    frames[1, 0, 0] = 30  # one pixel lights up, then goes dark again
    masks = np.zeros((3, 2, 2), bool)
    masks[:, 0, :] = True
    d = frame_differences(frames, masks)
    # each of the two steps changes 1 pixel x 3 channels by 30 out of 12 values
    assert d["whole_frame"] == pytest.approx(30 * 3 / 12) and d["frames"] == 3
    assert d["car"] == pytest.approx(30 * 3 / 6)  # over the 2 masked pixels x 3 channels
    with pytest.raises(ValueError, match="at least 2 frames"):
        frame_differences(frames[:1])
    steady = frames + 7.0  # a constant offset changes nothing between frames
    assert temporal_error(steady, frames, masks) == {"whole_frame": 0.0, "car": 0.0}
    still = np.zeros_like(frames)  # a renderer that ignores the motion misses all of it
    assert temporal_error(still, frames, masks)["whole_frame"] == pytest.approx(d["whole_frame"])


def eval_here(*args) -> subprocess.CompletedProcess:
    """`iae-eval ARGS` that must fail with a one-line error, in this process."""
    from eval.cli import main

    return invoke_here(main, *args)


@pytest.mark.blender
def test_video_of_r_on_the_path_and_its_flicker_relative_to_cycles(paths, tmp_path):
    run = tmp_path / "run"  # trained in this process: the commands below are the subject
    tiny_fit(run, tiny_intrinsics(tmp_path / "blobs"), tiny_photos(tmp_path / "photos"), 2)
    video = tmp_path / "R.mp4"
    run_train("render", "--run", str(run), "--intrinsics", str(paths / "pbr"), "--out", str(tmp_path / "frames"),
              "--video", str(video), "--side-by-side", "--quiet")
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    assert sum(1 for _ in reader) == FRAMES
    assert meta["size"] == (5 * 64 + 4 * 2, 32)  # normal | albedo | reflection | R | Cycles, 2-px gaps
    gif = tmp_path / "R.gif"
    run_train("render", "--run", str(run), "--intrinsics", str(paths / "intr"), "--out", str(tmp_path / "f2"),
              "--video", str(gif), "--quiet")
    from PIL import Image

    assert Image.open(gif).n_frames == FRAMES
    # the orbit strip: R of the run beside Cycles, and with --decompose H's normal and albedo of Cycles' frames
    strip = [sys.executable, str(ROOT / "bench" / "turntable_strip.py"), "--intrinsics", str(paths / "intr"),
             "--pbr", str(paths / "pbr"), "--every", "2"]
    for name, extra in (("plain", []), ("dec", ["--decompose"])):
        subprocess.run(strip + extra + ["--out", str(tmp_path / f"{name}.png"), f"tiny={run}"], cwd=ROOT, check=True,
                       capture_output=True)
    plain, dec = (np.asarray(Image.open(tmp_path / f"{n}.png")) for n in ("plain", "dec"))
    w = (plain.shape[1] - 4 * 2) // 5  # normal | albedo | reflection | R | Cycles, 2-px gaps
    assert dec.shape[0] == plain.shape[0] and dec.shape[1] == plain.shape[1] + 2 * (w + 2)
    assert np.array_equal(dec[:, :plain.shape[1]], plain)  # the columns before H's are the plain strip's
    assert dec[20:, plain.shape[1]:].std() > 0  # H's panels drawn, not blank
    bad = subprocess.run(strip[:4] + ["--decompose", "--out", str(tmp_path / "x.png"), f"tiny={run}"], cwd=ROOT,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--decompose reads Cycles' frames" in bad.stderr
    # H's figures at every checkpoint on a set no probe saw (bench/checkpoint_curve.py); a rerun resumes
    curve = tmp_path / "curve.jsonl"
    cmd = [sys.executable, str(ROOT / "bench" / "checkpoint_curve.py"), str(run), "--sets", str(paths / "pbr"),
           "--out", str(curve), "--plot", str(tmp_path / "curve.png")]
    subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
    rows = [json.loads(line) for line in curve.read_text().splitlines()]
    steps = sorted(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("step_*.safetensors"))
    assert steps and [r["step"] for r in rows] == steps and {r["set"] for r in rows} == {str(paths / "pbr")}
    # the constant predictor's normal error, from the set's own normals: the angle to the camera axis on the car
    from train.probe import load_probe

    probe = load_probe(paths / "pbr", 32, 64, limit=None)
    n, on = torch.nn.functional.normalize(probe.maps[:, 0:3], dim=1), probe.masks[:, 0] >= 0.5
    ang = torch.rad2deg(torch.acos(n[:, 2].clamp(-1, 1)))
    keep = on.flatten(1).any(1)
    want = float(((ang * on).sum((1, 2)) / on.sum((1, 2)).clamp_min(1))[keep].mean())
    assert rows[-1]["const_normal_deg"] == pytest.approx(want, abs=0.01)
    assert 0 < rows[-1]["normal_deg"] < 180 and rows[-1]["prior_normal_deg"] != rows[-1]["const_normal_deg"]
    before = curve.read_text()
    subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
    assert curve.read_text() == before and Image.open(tmp_path / "curve.png").size[0] > 0
    # the rows at one step as a Markdown table: H and the prior per run, the constant per set
    md = subprocess.run([sys.executable, str(ROOT / "bench" / "checkpoint_curve.py"), "--replot", str(curve),
                         "--table", str(steps[-1]), "--label", f"{run}=mine"], cwd=ROOT, check=True,
                        capture_output=True, text=True).stdout.splitlines()
    last = rows[-1]
    assert "| mine | constant |" in md[0] and len(md) == 3
    assert md[2] == (f"| pbr | {last['normal_deg']:.1f} ({last['prior_normal_deg']:.1f}) | "
                     f"{last['const_normal_deg']:.1f} |")
    bad = run_train("render", "--run", str(run), "--intrinsics", str(paths / "intr"), "--out", str(tmp_path / "f3"),
                    "--video", str(tmp_path / "R.avi"), check=False)
    assert bad.returncode and "expected a file ending in .mp4 or .gif" in bad.stderr
    # a folder that cannot take the video fails before any frame, naming why (as root a
    # read-only folder is writable, so the folder here is a file; /sys stands for read-only where it is)
    (tmp_path / "afile").write_text("x")
    for target in [tmp_path / "afile" / "R.mp4"] + ([Path("/sys/iae_test.mp4")] if Path("/sys").is_dir() else []):
        bad = run_train("render", "--run", str(run), "--intrinsics", str(paths / "intr"), "--out", str(tmp_path / "f4"),
                        "--video", str(target), check=False)
        assert bad.returncode == 1 and f"--video {target}: cannot write in {target.parent}" in bad.stderr, bad.stderr
        assert "No such file" not in bad.stderr and not (tmp_path / "f4").exists()
    out = tmp_path / "flicker.json"
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "flicker", "--run", str(run), "--path", str(paths / "pbr"),
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    (r,) = json.loads(out.read_text())
    assert r["cycles"]["frames"] == FRAMES and r["cycles"]["whole_frame"] > 0
    assert r["ratio_whole_frame"] == pytest.approx(r["renderer"]["whole_frame"] / r["cycles"]["whole_frame"])
    assert "Cycles (reference)" in proc.stdout
    # a PBR set that is not a camera path, and a path whose Cycles frames never change
    import shutil

    from .train_helpers import tiny_intrinsics as blobs

    not_a_path = blobs(tmp_path / "random_views", kind="pbr")
    (not_a_path / "dataset.json").write_text(json.dumps({**json.loads((paths / "pbr" / "dataset.json").read_text()),
                                                         "recipe": {"kind": "pbr", "orbit": None}}))
    still = tmp_path / "still"
    shutil.copytree(paths / "pbr", still)
    rows = [json.loads(line) for line in (still / "manifest.jsonl").read_text().splitlines()]
    for r in rows[1:]:
        shutil.copy(still / rows[0]["file"], still / r["file"])
        r["sha256"] = rows[0]["sha256"]
    (still / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    for folder, message in ((not_a_path, "not a camera path"), (still, "do not change along the path")):
        bad = eval_here("flicker", "--run", run, "--path", folder)
        assert bad.returncode == 1 and message in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
    # --intrinsics: R's input from another set of the same path; it must be that path and the
    # background the run was trained on (this run: black; the intrinsics turntable: environment)
    for given, message in ((paths / "intr", "trained on intrinsics with the 'black' background"),
                           (not_a_path, "not the camera path of --path")):
        bad = eval_here("flicker", "--run", run, "--path", paths / "pbr", "--intrinsics", given)
        assert bad.returncode == 1 and message in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
    again = tmp_path / "again.json"
    subprocess.run([sys.executable, "-m", "eval.cli", "flicker", "--run", str(run), "--path", str(paths / "pbr"),
                    "--intrinsics", str(paths / "pbr"), "--out", str(again)], cwd=ROOT, check=True, capture_output=True)
    assert json.loads(again.read_text())[0]["renderer"] == json.loads(out.read_text())[0]["renderer"]
    # a frame missing from the path: frames 1 and 3 are no neighbours, so the path is refused
    gap = tmp_path / "gap"
    shutil.copytree(paths / "pbr", gap)
    rows = [json.loads(line) for line in (gap / "manifest.jsonl").read_text().splitlines()]
    (gap / rows[2]["file"]).unlink()
    (gap / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for k, r in enumerate(rows) if k != 2))
    bad = eval_here("flicker", "--run", run, "--path", gap)
    assert bad.returncode == 1 and "--path" in bad.stderr and "frames 2 missing" in bad.stderr, bad.stderr


def test_one_ctrl_c_during_a_cycles_render_stops_cleanly_and_resumes(tmp_path):
    """Issue 19.9: the first Ctrl-C printed a traceback and the run went on to exit 0."""
    import signal
    import subprocess
    import sys
    import time

    from blender_gen.dataset import read_manifest

    from .conftest import ROOT

    out = tmp_path / "tt"
    args = ["turntable", "--out", str(out), "--car", "sedan_a", "--frames", "40", "--resolution", "64x32", "--pbr",
            "--samples", "4", "--quiet"]
    proc = subprocess.Popen([sys.executable, "-m", "blender_gen.cli", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 180
    while time.time() < deadline and len(read_manifest(out / "manifest.jsonl")) < 1:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=180)
    assert proc.returncode == 130, (proc.returncode, stderr[-500:])
    assert "Traceback" not in stderr and "run the same command again to resume" in stderr
    done = read_manifest(out / "manifest.jsonl")
    assert 1 <= len(done) < 40
    run_gen(*args)
    assert len(read_manifest(out / "manifest.jsonl")) == 40
