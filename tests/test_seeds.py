"""`iae-eval seeds`: several seeds' reports side by side, orderings per seed (eval/seeds.py)."""
from __future__ import annotations

import json

import pytest

from eval.seeds import compare, load


def _report(folder, full, shared, const=(40.0, 70.0, 55.0)):
    def dec(n, a, r):
        return {"normal_mean_deg": n, "albedo_l1_srgb255": a, "reflection_l1_srgb255": r}

    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({
        "runs": [{"label": "Ours (full)", "dec": dec(*full), "fid": {"fid": 200.0, "kid": 0.2}},
                 {"label": "Ours, w/o shared discr.", "dec": dec(*shared), "fid": None}],
        "references": [{"label": "Constant predictor", "dec": dec(*const), "fid": None}]}))
    return folder


def test_orderings_are_held_only_when_every_seed_agrees(tmp_path):
    a = _report(tmp_path / "cpu_s21" / "report", (38.0, 42.0, 36.0), (39.0, 49.0, 35.0))
    b = _report(tmp_path / "cpu_s22" / "report", (37.0, 45.0, 37.0), (36.0, 50.0, 38.0))
    names, rows = load([a, b / "results.json"])
    assert names == ["cpu_s21", "cpu_s22"]
    assert rows["Ours (full)"].values["KID x100"] == [20.0, 20.0]
    assert rows["Ours, w/o shared discr."].values["FID"] == [None, None]
    text = compare([a, b])
    assert "| Ours (full) | 38.0 / 37.0 | 42.0 / 45.0 | 36.0 / 37.0 | 200.0 / 200.0 | 20.0 / 20.0 |" in text
    assert "full better than Constant predictor on normals (deg): holds (margins 2.0 / 3.0)" in text
    assert "full better than Ours, w/o shared discr. on normals (deg): holds on 1 of 2 seeds (margins 1.0 / -1.0)" in text
    assert "full better than Ours, w/o shared discr. on albedo L1: holds (margins 7.0 / 5.0); paper: 52.74 against 54" in text
    assert "full better than Constant predictor on normals (deg): holds (margins 2.0 / 3.0)\n" in text  # no paper row
    assert "full better than Ours, w/o shared discr. on reflection L1: holds on 1 of 2 seeds" in text
    assert "spread across seeds (max - min): normals (deg) 1.0, albedo L1 3.0" in text
    assert "one seed: no spread yet" in compare([a])  # one seed settles nothing: said, not left blank


def test_a_folder_without_a_report_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="results.json"):
        load([tmp_path / "empty"])


def test_the_command_prints_and_writes_the_comparison(tmp_path):
    from click.testing import CliRunner

    from eval.cli import main

    a = _report(tmp_path / "s21" / "report", (38.0, 42.0, 36.0), (39.0, 49.0, 35.0))
    b = _report(tmp_path / "s22" / "report", (37.0, 45.0, 37.0), (36.0, 50.0, 38.0))
    res = CliRunner().invoke(main, ["seeds", str(a), str(b), "--out", str(tmp_path / "seeds.md")])
    assert res.exit_code == 0, res.output
    assert "Seeds, in this order: s21, s22" in res.output
    assert (tmp_path / "seeds.md").read_text() in res.output
    bad = CliRunner().invoke(main, ["seeds", str(tmp_path)])  # a folder that is no report
    assert bad.exit_code != 0 and "results.json" in bad.output


def _part(folder, runs, data_seed=23, train_count=2000):
    """A report of some runs of one seed, evaluated on sets like reproduce's (paths differ per session)."""
    def dec(n):
        return {"normal_mean_deg": n, "albedo_l1_srgb255": 40.0, "reflection_l1_srgb255": 35.0}

    sets = [{"role": role, "path": str(folder / role.strip("-")), "kind": kind, "count": count, "seed": seed,
             "cars": {"sedan_a": count}, "envmaps": {"sky_00": count}}
            for role, kind, count, seed in (("--data", "pbr", 48, data_seed), ("--real", "pbr", 400, 22),
                                            ("--intrinsics", "intrinsics", 200, 24),
                                            (f"{runs[0][0]} training intrinsics", "intrinsics", train_count, 21))]
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({
        "runs": [{"label": label, "dec": dec(n), "fid": None} for label, n in runs],
        "references": [{"label": "Constant predictor", "dec": dec(40.0), "fid": None}],
        "datasets": sets, "warnings": []}))
    return folder


def test_parts_of_one_seed_merge_only_when_evaluated_on_the_same_sets(tmp_path):
    from eval.seeds import merge

    a = _part(tmp_path / "session1", [("Ours (full)", 38.0), ("Ours, w/o decomp. cycle", 36.0)])
    b = _part(tmp_path / "session2", [("Ours, w/o A", 35.0)])
    joined = merge([a, b / "results.json"])
    assert [r["label"] for r in joined["runs"]] == ["Ours (full)", "Ours, w/o decomp. cycle", "Ours, w/o A"]
    assert [r["label"] for r in joined["references"]] == ["Constant predictor"]
    with pytest.raises(ValueError, match="also in"):  # one run reported twice
        merge([a, a])
    c = _part(tmp_path / "other_data", [("Ours, w/o N", 39.0)], data_seed=99)
    with pytest.raises(ValueError, match=r"--data set differs .* in seed"):
        merge([a, c])
    d = _part(tmp_path / "smaller_training_set", [("Ours, w/o F", 41.0)], train_count=1000)
    with pytest.raises(ValueError, match=r"training intrinsics differ .* in count"):
        merge([a, d])


def test_merged_parts_feed_the_seeds_comparison(tmp_path):
    from click.testing import CliRunner

    from eval.cli import main

    a = _part(tmp_path / "p1", [("Ours (full)", 38.0)])
    b = _part(tmp_path / "p2", [("Ours, w/o A", 35.0)])
    res = CliRunner().invoke(main, ["merge", str(a), str(b), "--out", str(tmp_path / "cpu_s22.json")])
    assert res.exit_code == 0, res.output
    assert "2 runs (Ours (full), Ours, w/o A) from 2 part(s)" in res.output
    text = CliRunner().invoke(main, ["seeds", str(tmp_path / "cpu_s22.json")]).output
    assert "Seeds, in this order: cpu_s22" in text
    assert "full better than Ours, w/o A on normals (deg): fails (margins -3.0); the paper has no figure for it" in text
    bad = CliRunner().invoke(main, ["merge", str(a), str(a), "--out", str(tmp_path / "x.json")])
    assert bad.exit_code != 0 and "also in" in bad.output and not (tmp_path / "x.json").exists()


def test_merge_draws_the_joined_reports_pictures_from_the_parts_folders(tmp_path):
    """`merge --grids`: R's renders of every part's runs side by side, and every run's H on the
    same Table-3 images, from the parts' report folders (no model is loaded)."""
    import shutil

    import numpy as np
    from click.testing import CliRunner
    from PIL import Image

    from eval.cli import main

    from .train_helpers import tiny_intrinsics

    intr = tiny_intrinsics(tmp_path / "fid_intrinsics", n=3, seed=4)
    pbr = tiny_intrinsics(tmp_path / "table3", n=2, seed=5, kind="pbr")
    colours = {"Ours (full)": (200, 30, 30), "Ours, w/o A": (30, 200, 30)}
    parts = []
    for name, (label, colour) in zip(("p1", "p2"), colours.items()):
        folder = _part(tmp_path / name, [(label, 38.0)])
        info = json.loads((folder / "results.json").read_text())
        for d in info["datasets"]:  # the sets a report of these parts was evaluated on
            d["path"] = str({"--intrinsics": intr, "--data": pbr}.get(d["role"], d["path"]))
        (folder / "results.json").write_text(json.dumps(info))
        run = folder / "runs" / f"00_{name}"
        (run / "rendered").mkdir(parents=True)
        for j in range(3):
            Image.new("RGB", (64, 32), colour).save(run / "rendered" / f"{j:06d}.png")
        shutil.copytree(pbr, run / "predictions")  # perfect predictions
        parts.append(folder)
    out = tmp_path / "grids"
    res = CliRunner().invoke(main, ["merge", *map(str, parts), "--out", str(tmp_path / "s.json"), "--grids", str(out),
                                    "--grid-rows", "2"])
    assert res.exit_code == 0, res.output
    renders = np.asarray(Image.open(out / "render_grid.png"))
    assert renders.shape == (18 + 2 * 128, 256 * (3 + 2), 3)  # normal, albedo, reflection, then the two runs
    for c, colour in enumerate(colours.values(), start=3):
        assert np.abs(renders[18 + 64, c * 256 + 128].astype(int) - colour).max() <= 2
    dec = np.asarray(Image.open(out / "decomposition_grid.png"))
    assert dec.shape == (18 + 2 * 3 * 128, 256 * (2 + 2), 3)  # image, ground truth, then the two runs
    truth, first_run = dec[18:, 256:512].astype(int), dec[18:, 512:768].astype(int)
    truth[:, :60], first_run[:, :60] = 0, 0  # the layer names are written over the truth column
    assert np.abs(truth - first_run).mean() < 1.0  # perfect predictions look like the truth
    # a results.json without its report folder cannot be drawn: a clear error, nothing written
    lone = tmp_path / "lone"
    lone.mkdir()
    shutil.copy(parts[1] / "results.json", lone / "results.json")
    bad = CliRunner().invoke(main, ["merge", str(parts[0]), str(lone), "--out", str(tmp_path / "t.json"),
                                    "--grids", str(tmp_path / "g2")])
    assert bad.exit_code != 0 and "no rendered/ and predictions/ of run 'Ours, w/o A'" in bad.output
    assert not (tmp_path / "t.json").exists() and not (tmp_path / "g2").exists()


def _edit(folder, fn):
    info = json.loads((folder / "results.json").read_text())
    fn(info)
    (folder / "results.json").write_text(json.dumps(info))
    return folder


def test_merge_compares_resolution_and_content_and_says_the_steps(tmp_path):
    from eval.seeds import merge

    def resolution(r):
        def edit(info):
            for d in info["datasets"]:
                d.update(resolution=list(r) if d["role"] == "--data" else [128, 64], content_sha256="same")
        return edit

    a = _edit(_part(tmp_path / "a", [("Ours (full)", 38.0)]), resolution((256, 128)))
    b = _edit(_part(tmp_path / "b", [("Ours, w/o A", 35.0)]), resolution((512, 256)))
    with pytest.raises(ValueError, match=r"--data set differs .* in resolution"):
        merge([a, b])
    c = _edit(_part(tmp_path / "c", [("Ours, w/o A", 35.0)]), resolution((256, 128)))
    _edit(c, lambda info: info["datasets"][0].update(content_sha256="regenerated"))
    with pytest.raises(ValueError, match=r"--data set differs .* in content_sha256"):
        merge([a, c])
    d = _edit(_part(tmp_path / "d", [("Ours, w/o A", 35.0)]), resolution((256, 128)))
    _edit(a, lambda info: info["runs"][0].update(step=5000))
    _edit(d, lambda info: info["runs"][0].update(step=20))
    joined = merge([a, d])
    assert [p["path"] for p in joined["parts"]] == [str(a), str(d)] and joined["parts"][1]["datasets"]
    assert any("different steps: Ours (full) 5000, Ours, w/o A 20" in w for w in joined["warnings"])


def test_seeds_refuses_one_report_twice_and_mixed_budgets(tmp_path):
    def run(seed, step=5000, size=(64, 128), sha=None):
        def edit(info):
            for k, r in enumerate(info["runs"]):
                r.update(seed=seed, step=step, size=list(size), trained_on=["intr", "real"], run=f"/runs/{r['label']}",
                         checkpoint_sha256=f"{sha or seed}-{k}")
        return edit

    a = _edit(_part(tmp_path / "s21" / "report", [("Ours (full)", 38.0)]), run(21))
    with pytest.raises(ValueError, match="named twice"):
        load([a, a / "results.json"])
    copy = _edit(_part(tmp_path / "copy" / "report", [("Ours (full)", 38.0)]), run(21))
    with pytest.raises(ValueError, match="also in"):  # the same checkpoint's figures under another name
        load([a, copy])
    _edit(copy, run(21, sha="x"))  # a retraining: same seed, same data
    with pytest.raises(ValueError, match="same sets"):
        load([a, copy])
    short = _edit(_part(tmp_path / "short" / "report", [("Ours (full)", 38.0)]), run(22, step=20, size=(32, 64)))
    with pytest.raises(ValueError, match=r"step 20, training 32x64, .*, but at step 5000, training 64x128"):
        load([a, short])
    b = _edit(_part(tmp_path / "s22" / "report", [("Ours (full)", 37.0)]), run(22))
    assert load([a, b])[0] == ["s21", "s22"]
    joined = tmp_path / "joined.json"
    joined.write_text((a / "results.json").read_text())  # a merge holding the part beside it
    with pytest.raises(ValueError, match="also in"):
        load([a, joined])
