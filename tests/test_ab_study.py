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
    s = summarise([answers], page.parent / "study.json")
    ab = next(r for r in s["rows"] if r["kind"] == "AB")
    assert ab["n"] == 4 and ab["k"] == sum(e == "A" for e, p in zip(expected, key["pairs"]) if p["kind"] == "AB")


def _key(path, study, kind, n):
    """A study key with n pairs of one kind, first method on the left."""
    first, second = {"AB": ("A", "B"), "AR": ("A", "real"), "BR": ("B", "real")}[kind]
    path.write_text(json.dumps({"schema": "iae-ab-study/1", "study": study,
                                "labels": {"A": "ours", "B": "MUNIT", "real": "real photo"},
                                "pairs": [{"pair": i, "kind": kind, "left": first, "right": second} for i in range(n)]}))
    return path


def _answers(path, study, kind, chosen_first, n, participant="p", labels=None):
    first, second = {"AB": ("A", "B"), "AR": ("A", "real"), "BR": ("B", "real")}[kind]
    rows = [{"pair": i, "kind": kind, "left": first, "right": second, "choice": "left" if i < chosen_first else "right",
             "chosen": first if i < chosen_first else second, "ms": 900} for i in range(n)]
    path.write_text(json.dumps({"schema": "iae-ab-study/1", "study": study, "participant": participant,
                                "labels": labels or {"A": "ours", "B": "MUNIT", "real": "real photo"}, "answers": rows}))
    return path


def test_summary_of_known_answers_gives_known_ratios_and_wilson_intervals(tmp_path):
    key = _key(tmp_path / "study.json", "s1", "AB", 40)
    f1 = _answers(tmp_path / "1.json", "s1", "AB", 30, 40, "ann")
    f2 = _answers(tmp_path / "2.json", "s1", "AB", 10, 20, "bob")
    s = summarise([f1, f2], key)
    (row,) = s["rows"]
    assert (row["k"], row["n"], row["comparison"]) == (40, 60, "ours vs MUNIT")
    assert row["ratio"] == pytest.approx(2 / 3) and row["per_participant"] == [0.75, 0.5]
    # Wilson 95% for 40/60, by hand: centre (2/3 + z²/120) / (1 + z²/60) = 0.6566, half-width 0.1161
    assert row["ci95"] == pytest.approx([0.5406, 0.7727], abs=1e-4)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(1.0) and wilson(0, 0) == (0.0, 1.0)
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", "--study", str(key), str(f1), str(f2)],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0 and "ours 66.7%" in proc.stdout and "[54.1, 77.3]" in proc.stdout


def test_summary_counts_each_participant_and_pair_once_with_the_studys_labels(tmp_path):
    """Issue 19.7: the same file three times, 100,000 answers for a 9-pair study, labels edited in
    an answer file, answers for pairs the study does not have."""
    key = _key(tmp_path / "study.json", "s1", "AB", 9)
    f1 = _answers(tmp_path / "1.json", "s1", "AB", 9, 9, "ann")
    with pytest.raises(StudyError, match="the same answers as"):
        summarise([f1, f1, f1], key)
    flood = tmp_path / "flood.json"
    data = json.loads(f1.read_text())
    data["answers"] = data["answers"] * 11112
    flood.write_text(json.dumps(data))
    with pytest.raises(StudyError, match="pair 0 is answered twice"):
        summarise([flood], key)
    swapped = _answers(tmp_path / "2.json", "s1", "AB", 0, 9, "bob", labels={"A": "CycleGAN", "B": "ours", "real": "x"})
    for order in ([f1, swapped], [swapped, f1]):
        (row,) = summarise(order, key)["rows"]
        assert row["comparison"] == "ours vs MUNIT" and row["k"] == 9 and row["n"] == 18
    extra = _answers(tmp_path / "3.json", "s1", "AB", 3, 12, "cy")
    with pytest.raises(StudyError, match="answer 9: pair 9 is not in this study"):
        summarise([extra], key)
    again = _answers(tmp_path / "4.json", "s1", "AB", 2, 9, "ann")
    with pytest.raises(StudyError, match="participant 'ann' already answered"):
        summarise([f1, again], key)
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", str(f1)], cwd=ROOT, capture_output=True,
                          text=True)
    assert proc.returncode == 2 and "--study" in proc.stderr


def test_answers_of_another_study_or_malformed_files_are_refused(tmp_path, study):
    key = _key(tmp_path / "study.json", "s1", "AB", 4)
    f1 = _answers(tmp_path / "1.json", "s1", "AB", 3, 4)
    f2 = _answers(tmp_path / "2.json", "s2", "AB", 3, 4)
    with pytest.raises(StudyError, match=r"2.json: answers to study 's2', not 's1'"):
        summarise([f1, f2], key)
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema": "iae-ab-study/1", "study": "s1", "answers": [{"kind": "AB", "chosen": "real"}]}')
    with pytest.raises(StudyError, match=r"bad.json: answer 0: 'pair' must be a pair number of this study, got null"):
        summarise([bad], key)
    # one message per field, naming it
    good = json.loads(f1.read_text())
    first = good["answers"][0]
    for change, message in (({"kind": "Ar"}, "'kind' is \"Ar\", but pair"), ({"chosen": "Z"}, "'chosen' is \"Z\", but pair"),
                            ({"pair": "0"}, "'pair' must be a pair number"), ({"pair": True}, "'pair' must be a pair number")):
        edited = tmp_path / "edited.json"
        edited.write_text(json.dumps({**good, "answers": [{**first, **change}]}))
        with pytest.raises(StudyError, match=message):
            summarise([edited], key)
    edited.write_text(json.dumps({**good, "answers": ["x"]}))
    with pytest.raises(StudyError, match="answer 0 is not a JSON object"):
        summarise([edited], key)
    edited.write_text(json.dumps({k: v for k, v in good.items() if k != "study"}))
    with pytest.raises(StudyError, match="'study' missing"):
        summarise([edited], key)
    mistyped = tmp_path / "mistyped.json"
    mistyped.write_text('{"schema": "iae-ab-study/1", "study": "s1", "participant": 7, "answers": []}')
    with pytest.raises(StudyError, match="'participant' must be a string"):
        summarise([mistyped], key)
    (tmp_path / "torn.json").write_text('{"schema": "iae-ab')
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", "--study", str(key),
                           str(tmp_path / "torn.json")], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1 and "torn.json: not a JSON answer file" in proc.stderr and "Traceback" not in proc.stderr
    nokey = subprocess.run([sys.executable, "-m", "eval.cli", "ab-summary", "--study", str(f1), str(f1)], cwd=ROOT,
                           capture_output=True, text=True)
    assert nokey.returncode == 1 and "not the study.json" in nokey.stderr and "Traceback" not in nokey.stderr
    with pytest.raises(StudyError, match=r"--b .*: no such folder of images"):
        build_study(tmp_path / "a", tmp_path / "nothing", tmp_path / "s", 2)


def test_any_label_text_is_safe_in_the_page_and_too_many_pairs_are_refused(tmp_path, headless_chromium):
    """Issue 19.8: a label '<!--<script>' broke the page; a label '__TITLE__' was replaced by the title."""
    names = [f"{i:06d}" for i in range(3)]
    a = _images(tmp_path / "a", names, (200, 40, 40))
    b = _images(tmp_path / "b", names, (40, 200, 40))
    labels = ("__TITLE__", "<!--<script></script>&amp;")
    page = build_study(a, b, tmp_path / "study", pairs=3, seed=1, label_a=labels[0], label_b=labels[1], height=40)
    flags = headless_chromium + ["--virtual-time-budget=5000", "--dump-dom"]
    dom = subprocess.run(flags + [page.resolve().as_uri() + "#simulate=LRL"], capture_output=True, text=True,
                         timeout=120).stdout
    check = re.search(r'id="selfcheck"[^>]*>images=(\d+) broken=(\d+) errors=(\d+)<', dom)
    assert check and check.groups()[1:] == ("0", "0"), dom[-800:]
    exported = re.search(r'<pre id="export"[^>]*>(.*?)</pre>', dom, re.S).group(1)
    import html as _html
    data = json.loads(_html.unescape(exported))
    assert (data["labels"]["A"], data["labels"]["B"]) == labels and len(data["answers"]) == 3
    with pytest.raises(StudyError, match=r"--pairs 4: the images give only 3 distinct A-vs-B scenes"):
        build_study(a, b, tmp_path / "s2", pairs=4)
