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
    assert "full better than Ours, w/o shared discr. on albedo L1: holds (margins 7.0 / 5.0)" in text
    assert "full better than Ours, w/o shared discr. on reflection L1: holds on 1 of 2 seeds" in text
    assert "spread across seeds (max - min): normals (deg) 1.0, albedo L1 3.0" in text


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
