"""Shared fixtures: tiny datasets rendered once per test session."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_ASSETS = ROOT.parent / "shared" / "assets"

# `make test` runs the modules in pytest-xdist workers, one per core. Each worker gets its share of
# the cores (set before any test module imports torch): two torch processes with two OpenMP threads
# each on two cores spin against each other, and a 0.45 s training step was measured at 15-20 s.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
TEST_THREADS = max(1, len(os.sched_getaffinity(0)) // _WORKERS) if _WORKERS > 1 else 2
if _WORKERS > 1:
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(TEST_THREADS)


def bench_module(name: str):
    """A script of bench/ imported as a module (they run as scripts, so bench/ is no package); the
    search path is restored afterwards, so no test leaves bench/ on it for the others."""
    import importlib

    sys.path[:0] = [str(ROOT / "bench")]
    try:
        return importlib.import_module(name)
    finally:
        del sys.path[0]


def invoke_here(main, *args, env: dict | None = None) -> subprocess.CompletedProcess:
    """A click command line run in this process, as a CompletedProcess (exit code, stdout, stderr).

    For the error paths: a command that must stop early with a one-line message is checked
    without a fresh interpreter importing torch (seconds per call). An exception that escapes
    the command is appended to stderr as its traceback, so "Traceback" checks keep their meaning."""
    import traceback

    from click.testing import CliRunner

    result = CliRunner().invoke(main, [str(a) for a in args], env=env, catch_exceptions=True)
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "Traceback (most recent call last):\n" + "".join(traceback.format_exception(result.exception))
    return subprocess.CompletedProcess(list(args), result.exit_code, result.stdout, stderr)


def assets_mark(sub: str):
    """Tests on the shared CC0 assets: skipped on a machine without them, but never in CI,
    where `../shared` is always beside the clone and a missing folder is a failure to see."""
    missing = not (SHARED_ASSETS / sub).is_dir()
    if missing and os.environ.get("CI"):
        return pytest.mark.usefixtures("_fail_missing_assets")
    return pytest.mark.skipif(missing, reason=f"shared CC0 assets not present ({SHARED_ASSETS / sub})")


@pytest.fixture
def _fail_missing_assets():
    pytest.fail(f"{SHARED_ASSETS} is missing: CI runs with ../shared beside the clone")


@pytest.fixture
def headless_chromium(tmp_path) -> list[str]:
    """The command line of a headless Chromium with a fresh profile (append flags and a URL).

    Skipped where no Chromium is installed, but a failure in CI, whose .ci/run installs it."""
    browser = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    if browser is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing in CI: .ci/run installs Debian's chromium")
        pytest.skip("chromium not installed (apt-get install chromium)")
    return [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run",
            f"--user-data-dir={tmp_path / 'chromium-profile'}"]


def run_gen(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    """Run `iae-gen` in a fresh process (as a user would) and capture its output."""
    cmd = [sys.executable, "-m", "blender_gen.cli", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def tiny_intrinsics(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "intr"
    run_gen("intrinsics", "--out", str(out), "--count", "4", "--resolution", "64x32", "--seed", "3", "--quiet")
    return out


@pytest.fixture(scope="module")
def renderer():
    """An in-process intrinsics renderer at 128x64, fresh for each test module: Blender holds one
    scene per process, so a renderer made by another module would have replaced it."""
    from blender_gen.recipe import Recipe
    from blender_gen.render import SampleRenderer

    r = SampleRenderer(Recipe(kind="intrinsics", seed=11, width=128, height=64), threads=TEST_THREADS)
    yield r
    r.close()
