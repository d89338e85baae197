"""Framing: cameras drawn for a coverage range, the photos' framing estimated, the own-data plan
matching the two (close-framed PBR renders stand in for photos)."""
from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from blender_gen.camera import CameraRanges, coverage, project, sample_camera
from blender_gen.cars import build_car, load_catalogue
from blender_gen.recipe import Recipe
from eval.framing import coverage_range, estimate_framing, photo_coverage, to_frame

from .conftest import run_gen

ROOT = Path(__file__).resolve().parents[1]


def _points(name: str) -> np.ndarray:
    return np.concatenate([m.verts for m in build_car(load_catalogue()[name]).values()])


@pytest.mark.parametrize("car", ["sedan_a", "van_b"])
def test_framed_cameras_keep_the_car_whole_within_the_coverage_range(car):
    pts = _points(car)
    ranges = CameraRanges(min_coverage=0.35, max_coverage=0.6)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    rng = np.random.default_rng(4)
    covers = []
    for _ in range(60):
        pose = sample_camera(rng, pts, 256, 128, ranges)
        c = coverage(pts, pose, 256, 128)
        assert 0.35 - 1e-6 <= c <= 0.6 + 1e-6
        xy, depth = project(pts, pose, 256, 128)
        m = ranges.margin * 256
        assert (depth > 0.1).all() and xy.min() >= m - 1e-6 and xy[:, 0].max() <= 256 - m + 1e-6
        assert xy[:, 1].max() <= 128 - m + 1e-6
        r = np.hypot(*(np.array(pose.location[:2]) - centre[:2]))
        assert ranges.radius_min - 1e-6 <= r <= ranges.radius_max + 1e-6
        assert ranges.height_min <= pose.location[2] <= ranges.height_max
        covers.append(c)
    lo, hi = np.percentile(covers, [10, 90])
    assert lo < 0.42 and hi > 0.48  # spread over the range, not piled at one end
    again = sample_camera(np.random.default_rng(4), pts, 256, 128, ranges)
    assert again == sample_camera(np.random.default_rng(4), pts, 256, 128, ranges)  # seeded
    # the paper's rule draws farther cameras: its median coverage is lower
    rng = np.random.default_rng(4)
    paper = [coverage(pts, sample_camera(rng, pts, 256, 128), 256, 128) for _ in range(60)]
    assert np.median(paper) < np.median(covers)


def test_a_coverage_range_is_part_of_the_recipe_and_checked():
    plain = Recipe(kind="intrinsics", seed=0, width=128, height=64)
    assert "max_coverage" not in plain.identity()["camera"]  # sets made before the option keep their identity
    framed = replace(plain, camera=CameraRanges(min_coverage=0.3, max_coverage=0.7))
    assert framed.identity()["camera"]["max_coverage"] == 0.7
    with pytest.raises(ValueError, match="max"):
        CameraRanges(min_coverage=0.5, max_coverage=0.4).validate()
    bad = run_gen("intrinsics", "--out", "unused_never_made", "--count", "1", "--min-coverage", "0.5",
                  "--max-coverage", "0.4", check=False)
    assert bad.returncode == 1 and "--max-coverage" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert not Path(ROOT / "unused_never_made").exists()


def test_the_estimate_finds_a_car_shaped_region_and_skips_unreadable_photos(tmp_path):
    rng = np.random.default_rng(0)
    folder = tmp_path / "photos"
    folder.mkdir()
    truth = []
    for k, (w, h) in enumerate([(320, 160), (200, 100), (640, 320), (256, 128)]):
        y = np.linspace(0, 1, h)[:, None, None]
        img = (np.concatenate([0.6 + 0.3 * y, 0.7 + 0.2 * y, 0.8 - 0.1 * y], axis=-1) * np.ones((h, w, 3)))
        bw, bh = int(w * (0.35 + 0.1 * k)), int(h * (0.4 + 0.1 * k))
        x0, y0 = (w - bw) // 2 + int(rng.integers(-5, 5)), (h - bh) // 2
        img[y0:y0 + bh, x0:x0 + bw] = rng.uniform(0.05, 0.3, 3) + rng.normal(0, 0.02, (bh, bw, 3))
        Image.fromarray((img.clip(0, 1) * 255).astype(np.uint8)).save(folder / f"car_{k}.jpg", quality=92)
        truth.append(bw * bh / (w * h))
    (folder / "broken.jpg").write_bytes(b"not a jpeg")
    found = estimate_framing(sorted(folder.iterdir()), progress=False)
    assert found.skipped == (str(folder / "broken.jpg"),)
    assert np.allclose(sorted(found.coverages), sorted(truth), atol=0.05)
    assert "4 photos" in found.describe() and "1 unreadable skipped" in found.describe()
    assert found.gen_options() == ["--min-coverage", f"{found.low:.2f}", "--max-coverage", f"{found.high:.2f}"]
    flat = to_frame(np.full((90, 90, 3), 0.5, np.float32))
    assert flat.shape == (64, 128, 3) and photo_coverage(flat) == 0.0  # nothing to find: no error
    assert coverage_range([0.5] * 5) == (0.45, 0.55)  # at least 0.1 wide
    assert coverage_range([0.01, 0.02, 0.99, 0.99]) == (0.05, 0.9)  # the car stays whole in the frame
    with pytest.raises(ValueError, match="no readable photo among 1 .*broken.jpg"):
        estimate_framing([folder / "broken.jpg"], progress=False)
    # the command: figures, the iae-gen options, the boxes drawn for a person to check, the JSON
    from click.testing import CliRunner

    from eval.cli import main

    res = CliRunner().invoke(main, ["framing", str(folder), "--quiet", "--sheet", str(tmp_path / "boxes.png"),
                                    "--out", str(tmp_path / "framing.json")])
    assert res.exit_code == 0, res.output
    assert f"--min-coverage {found.low:.2f} --max-coverage {found.high:.2f}" in res.output
    assert f"skipped (unreadable): {folder / 'broken.jpg'}" in res.output
    assert Image.open(tmp_path / "boxes.png").size[0] > 256
    import json

    assert json.loads((tmp_path / "framing.json").read_text())["range"] == [found.low, found.high]
    (tmp_path / "empty").mkdir()
    empty = CliRunner().invoke(main, ["framing", str(tmp_path / "empty")])
    assert empty.exit_code == 1 and "no .jpg/.png/.webp/.bmp/.tif photos" in empty.output
    (tmp_path / "empty" / "IMG_0001.HEIC").write_bytes(b"\0" * 64)  # a phone's default format
    heic = CliRunner().invoke(main, ["framing", str(tmp_path / "empty")])
    assert heic.exit_code == 1 and "1 photo(s) in formats not read here (.heic; first IMG_0001.HEIC)" in heic.output
    # with the progress bar on and stderr in a log file, the error is a line of its own, not
    # appended to the bar's carriage-returned line
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.jpg").write_bytes(b"junk")
    log = subprocess.run([sys.executable, "-m", "eval.cli", "framing", str(tmp_path / "junk")],
                         capture_output=True, cwd=ROOT)  # bytes: text mode would turn the bar's \r into \n
    err = log.stderr.decode()
    assert log.returncode == 1 and "framing:" in err  # the bar was drawn
    assert any(line.startswith("Error: no readable photo among 1") for line in err.split("\n")), err


@pytest.mark.blender
def test_own_data_plan_frames_its_sets_like_close_framed_photos(tmp_path):
    """Close-framed PBR renders stand in for photos: the estimate recovers their framing (their
    material layers give the truth) and reproduce's plan draws every generated set's cameras to match."""
    close, loose = tmp_path / "close", tmp_path / "loose"
    common = ["--count", "8", "--resolution", "256x128", "--samples", "2", "--seed", "5", "--quiet"]
    run_gen("pbr", "--out", str(close), "--min-coverage", "0.45", "--max-coverage", "0.7", *common)
    run_gen("pbr", "--out", str(loose), *common)
    from blender_gen.conversions import linear_to_srgb
    from blender_gen.dataset import open_dataset
    from eval.framing import box_coverage, mask_box

    medians = {}
    for name, root in (("close", close), ("loose", loose)):
        ds = open_dataset(root)
        photos = tmp_path / f"{name}_photos"
        photos.mkdir()
        truth = []
        for i in range(len(ds)):
            s = ds.load(i, ["rgb", "material"])
            rgb8 = (linear_to_srgb(s["rgb"][..., :3]) * 255 + 0.5).astype(np.uint8)
            size = [(256, 128), (300, 150), (512, 256)][i % 3]  # photos of mixed sizes
            Image.fromarray(rgb8).resize(size, Image.BICUBIC).save(photos / f"photo_{i}.jpg", quality=90)
            truth.append(box_coverage(mask_box(s["material"][..., 0] > 0), s["material"].shape))  # glass too
        found = estimate_framing(sorted(photos.iterdir()), progress=False)
        medians[name] = np.median(found.coverages)
        assert abs(medians[name] - np.median(truth)) < 0.08, (name, found.coverages, truth)
        if name == "close":
            assert min(truth) >= 0.43 and max(truth) <= 0.72  # the renders keep the range asked for
            close_truth, close_photos = truth, photos
    assert medians["close"] > medians["loose"] + 0.1
    from eval.protocol import describe  # the report's data table says how each set was framed

    assert describe("--data", close).framing == "0.45-0.70"
    assert describe("--data", loose).framing == "paper's rule (>= 0.08)"
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full",
                           "--real", str(close_photos), "--out", str(tmp_path / "o"), "--dry-run"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "framing   your photos: the car fills" in proc.stdout
    line = next(x for x in proc.stdout.splitlines() if x.strip().startswith("cameras"))
    lo, hi = (float(v) for v in line.split("covering ")[1].split(" of")[0].split("-"))
    assert lo <= np.median(close_truth) <= hi and 0.3 <= lo < hi <= 0.8
    paper = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full",
                            "--real", str(close_photos), "--coverage", "paper", "--out", str(tmp_path / "o"),
                            "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert paper.returncode == 0 and "the paper's rule" in paper.stdout and "framing" not in paper.stdout
    bad = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--coverage", "0.8-0.3",
                          "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "--coverage" in bad.stderr and "0 <= LO < HI <= 1" in bad.stderr


def test_a_photo_is_read_upright_as_its_exif_orientation_says(tmp_path):
    """A phone's portrait photo is landscape pixels with EXIF orientation 6 (turn 90 degrees
    clockwise to view): training, decompose and the framing estimate must all see it upright."""
    from train.data import read_photo

    pixels = np.zeros((30, 60, 3), np.uint8)
    pixels[:, :20] = 255  # a white band on the stored image's left: on the upright photo's top
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(pixels).save(tmp_path / "portrait.jpg", exif=exif.tobytes(), quality=95)
    photo = read_photo(tmp_path / "portrait.jpg")
    assert photo.shape == (60, 30, 3)
    assert photo[:15].mean() > 0.9 and photo[-15:].mean() < 0.1
    Image.fromarray(pixels).save(tmp_path / "plain.jpg", quality=95)  # no tag: as stored
    assert read_photo(tmp_path / "plain.jpg").shape == (30, 60, 3)
    from eval.images import image_size

    (tmp_path / "plain.jpg").unlink()
    assert image_size(tmp_path) == (60, 30)  # the folder's first photo, upright


def test_a_sets_framing_column_names_coverage_paper_rule_or_orbit():
    from eval.protocol import framing_of

    assert framing_of({"camera": {"min_coverage": 0.4, "max_coverage": 0.7}}) == "0.40-0.70"
    assert framing_of({"camera": {"min_coverage": 0.08}}) == "paper's rule (>= 0.08)"
    assert framing_of({"camera": {"min_coverage": 0.08}, "orbit": {"radius": 6.0}}) == "turntable orbit"
    assert framing_of({}) == "-"


def test_a_car_no_camera_can_frame_is_named_in_one_line(tmp_path):
    # With several --cars one model may be too large (or the coverage too tight) for the camera
    # ranges: the error names that car and its size, so the user knows which one to drop.
    out = tmp_path / "never"
    res = run_gen("intrinsics", "--out", str(out), "--count", "1", "--cars", "van_b", "--resolution", "64x32",
                  "--min-coverage", "0.95", "--quiet", check=False)
    assert res.returncode == 1, res.stderr
    line = res.stderr.strip()
    assert len(line.splitlines()) == 1 and "car 'van_b' (" in line and "no valid camera" in line, line
    assert not (out / "dataset.json").exists() or '"complete": false' in (out / "dataset.json").read_text()
