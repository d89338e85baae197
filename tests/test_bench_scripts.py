"""Every benchmark script (`make bench`, the sweeps) imports: a renamed function once broke one
silently, since no test runs the benchmarks themselves."""
from __future__ import annotations

import subprocess
import sys

from .conftest import ROOT


def test_every_bench_script_imports():
    names = sorted(p.stem for p in (ROOT / "bench").glob("*.py") if p.stem != "__init__")
    assert "bench_pbr" in names and len(names) > 10
    code = "import importlib, sys\nsys.path[:0] = ['bench', '.']\n" + "".join(
        f"importlib.import_module({n!r})\n" for n in names)
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
