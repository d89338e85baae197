"""Issue 19, items 3 and 5: one writer per run folder, children that die with `reproduce`, and a
refused turntable that leaves its folder ready for the corrected command."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from .conftest import ROOT, run_gen
from .train_helpers import TINY, tiny_intrinsics, tiny_photos


def _wait_for(predicate, timeout: float = 120.0) -> None:
    end = time.time() + timeout
    while not predicate():
        if time.time() > end:
            raise AssertionError("timed out")
        time.sleep(0.2)


def test_a_second_training_of_one_run_folder_is_refused(tmp_path):
    intr, photos = tiny_intrinsics(tmp_path / "intr"), tiny_photos(tmp_path / "photos")
    run = tmp_path / "run"
    fit = [sys.executable, "-m", "train.cli", "fit", "--run-dir", str(run), "--config", "cpu-small", "--intrinsics",
           str(intr), "--real", str(photos), "--max-steps", "100000", "--quiet", *TINY]
    first = subprocess.Popen(fit, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: (run / "stats.jsonl").exists() or first.poll() is not None)
        assert first.poll() is None, first.communicate()
        second = subprocess.run(fit, cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert second.returncode == 1 and "Traceback" not in second.stderr
        assert f"--run-dir {run} is being written by pid {first.pid}" in second.stderr
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=120)
    assert first.returncode == 130, "the first training stops cleanly, checkpoint saved"
    # a refused first start leaves no folder behind
    bad = subprocess.run([sys.executable, "-m", "train.cli", "fit", "--run-dir", str(tmp_path / "new"), "--config",
                          "cpu-small", "--intrinsics", str(tmp_path / "missing"), "--real", str(photos), "--quiet"],
                         cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 1 and not (tmp_path / "new").exists()


def test_children_of_reproduce_die_with_it(tmp_path):
    """SIGKILL of the parent: its training child gets SIGTERM (PR_SET_PDEATHSIG) instead of living on."""
    pidfile = tmp_path / "child.pid"
    child = f"import os, time; open({str(pidfile)!r}, 'w').write(str(os.getpid())); time.sleep(120)"
    parent = (f"import sys; from pathlib import Path; from eval.reproduce import _run; "
              f"_run([sys.executable, '-c', {child!r}], Path({str(tmp_path / 'log.txt')!r}))")
    proc = subprocess.Popen([sys.executable, "-c", parent], cwd=ROOT)
    _wait_for(lambda: pidfile.exists() and pidfile.read_text())
    pid = int(pidfile.read_text())
    proc.kill()
    proc.wait()

    def gone() -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        with open(f"/proc/{pid}/stat") as fh:  # a zombie re-parented to init counts as gone
            return fh.read().split()[2] == "Z"

    _wait_for(gone, timeout=20)


def test_reproduce_refuses_a_run_named_twice():
    proc = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full,,full",
                           "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "--runs" in proc.stderr and "empty run name" in proc.stderr
    typo = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs", "full,fulll",
                           "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert typo.returncode == 2 and "fulll: unknown run" in typo.stderr
    twice = subprocess.run([sys.executable, "-m", "eval.cli", "reproduce", "--budget", "smoke", "--runs",
                            "full,no_dec,full", "--dry-run"], cwd=ROOT, capture_output=True, text=True)
    assert twice.returncode == 2 and "full named twice" in twice.stderr


@pytest.mark.blender
def test_a_refused_turntable_leaves_its_folder_for_the_corrected_command(tmp_path):
    out = tmp_path / "tt"
    args = ["turntable", "--out", str(out), "--car", "sedan_a", "--frames", "3", "--resolution", "64x32", "--quiet"]
    for bad in (["--radius", "0.5"], ["--radius", "nan"], ["--radius", "inf"], ["--height", "nan"]):
        proc = run_gen(*args, *bad, check=False)
        assert proc.returncode != 0 and "Traceback" not in proc.stderr, bad
        assert not (out / "dataset.json").exists(), bad
    run_gen(*args)
    assert (out / "dataset.json").exists()
