"""`iae-eval ab-study` / `ab-summary`: the page, the answers it exports, the ratios and intervals."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from eval.ab_study import StudyError, build_study, make_pairs, summarise, wilson

from .conftest import ROOT


def _images(root, names, colour, suffix=".png"):
    root.mkdir(parents=True)
    for k, name in enumerate(names):
        img = np.full((40, 80, 3), colour, np.uint8)
        img[10:30, 10 + k:40 + k] = 255 - np.array(colour, np.uint8)
        Image.fromarray(img).save(root / f"{name}{suffix}")
    return root


@pytest.fixture
def study(tmp_path):
    names = [f"{i:06d}" for i in range(6)]
    a = _images(tmp_path / "a", names, (200, 40, 40))
    b = _images(tmp_path / "b", names, (40, 200, 40))
    real = _images(tmp_path / "real", ["p1", "p2", "p3"], (40, 40, 200), ".jpg")
    page = build_study(a, b, tmp_path / "study", pairs=4, real=real, seed=3, label_a="ours", label_b="CycleGAN",
                       height=40)
    return page, json.loads((tmp_path / "study" / "study.json").read_text())


def test_pairs_are_balanced_randomised_and_show_the_same_scene_for_a_and_b(study):
    _, key = study
    pairs = key["pairs"]
    assert [sum(p["kind"] == k for p in pairs) for k in ("AB", "AR", "BR")] == [4, 4, 4]
    assert {p["kind"] for p in pairs[:4]} != {"AB"} or {p["kind"] for p in pairs[4:8]} != {"AB"}  # shuffled
    for p in pairs:
        assert {p["left"], p["right"]} == {"AB": {"A", "B"}, "AR": {"A", "real"}, "BR": {"B", "real"}}[p["kind"]]
        if p["kind"] == "AB":  # both renderers of one intrinsics sample
            assert os.path.basename(p["left_file"]) == os.path.basename(p["right_file"])
    lefts = [p["left"] for p in pairs]
    assert 0 < lefts.count("A") + lefts.count("B") < 16 and "real" in lefts  # sides drawn at random
    assert make_pairs.__doc__ and key["labels"]["A"] == "ours"


def test_the_page_loads_and_simulated_clicks_export_the_expected_answers(study, tmp_path, headless_chromium):
    page, key = study
    clicks = "LRLLRRLRLRRL"
    flags = headless_chromium + ["--virtual-time-budget=5000", "--dump-dom"]
    dom = subprocess.run(flags + [page.resolve().as_uri() + "#simulate=" + clicks], capture_output=True, text=True,
                         timeout=120).stdout
    check = re.search(r'id="selfcheck"[^>]*>images=(\d+) broken=(\d+) errors=(\d+)<', dom)
    assert check, dom[-800:]
    assert check.groups()[1:] == ("0", "0")
    exported = json.loads(re.search(r'<pre id="export"[^>]*>(.*?)</pre>', dom, re.S).group(1).replace("&quot;", '"'))
    assert exported["study"] == key["study"] and exported["participant"] == "simulated"
    expected = [p["left"] if c == "L" else p["right"] for p, c in zip(key["pairs"], clicks)]
    assert [a["chosen"] for a in exported["answers"]] == expected
    assert [a["pair"] for a in exported["answers"]] == list(range(12))
    answers = tmp_path / "answers.json"
    answers.write_text(json.dumps(exported))
    s = summarise([answers])
    ab = next(r for r in s["rows"] if r["kind"] == "AB")
    assert ab["n"] == 4 and ab["k"] == sum(e == "A" for e, p in zip(expected, key["pairs"]) if p["kind"] == "AB")


def _answers(path, study, kind, chosen_first, n, participant="p"):
    first, second = {"AB": ("A", "B"), "AR": ("A", "real"), "BR": ("B", "real")}[kind]
    rows = [{"pair": i, "kind": kind, "left": first, "right": second, "choice": "left" if i < chosen_first else "right",
             "chosen": first if i < chosen_first else second, "ms": 900} for i in range(n)]
    path.write_text(json.dumps({"schema": "iae-ab-study/1", "study": study, "participant": participant,
                                "labels": {"A": "ours", "B": "MUNIT", "real": "real photo"}, "answers": rows}))
    return path


def test_summary_of_known_answers_gives_known_ratios_and_wilson_intervals(tmp_path):
    f1 = _answers(tmp_path / "1.json", "s1", "AB", 30, 40, "ann")
    f2 = _answers(tmp_path / "2.json", "s1", "AB", 10, 20, "bob")
    s = summarise([f1, f2])
    (row,) = s["rows"]
    assert (row["k"], row["n"], row["comparison"]) == (40, 60, "ours vs MUNIT")
    assert row["ratio"] == pytest.approx(2 / 3) and row["per_participant"] == [0.75, 0.5]
    # Wilson 95% for 40/60, by hand: centre (2/3 + z²/120) / (1 + z²/60) = 0.6566, half-width 0.1161
    assert row["ci95"] == pytest.approx([0.5406, 0.7727], abs=1e-4)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(1.0) and wilson(0, 0) == (0.0, 1.0)
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", str(f1), str(f2)], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0 and "ours 66.7%" in proc.stdout and "[54.1, 77.3]" in proc.stdout


def test_answers_of_another_study_or_malformed_files_are_refused(tmp_path, study):
    f1 = _answers(tmp_path / "1.json", "s1", "AB", 3, 4)
    f2 = _answers(tmp_path / "2.json", "s2", "AB", 3, 4)
    with pytest.raises(StudyError, match=r"2.json: answers to study s2, not s1"):
        summarise([f1, f2])
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "iae-ab-study/1", "study": "s1", "answers": [{"kind": "AB", "chosen": "real"}]}')
    with pytest.raises(StudyError, match=r"bad.json: answer 0 is malformed"):
        summarise([bad])
    (tmp_path / "torn.json").write_text('{"schema": "iae-ab')
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", str(tmp_path / "torn.json")], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 1 and "torn.json: not a JSON answer file" in proc.stderr and "Traceback" not in proc.stderr
    with pytest.raises(StudyError, match=r"--b .*: no such folder of images"):
        build_study(tmp_path / "a", tmp_path / "nothing", tmp_path / "s", 2)
