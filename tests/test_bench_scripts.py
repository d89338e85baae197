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


def test_every_sweep_variant_is_a_valid_config():
    """Each variant of the sweep files, with its file's `base` (the defaults it was measured under),
    loads: a default that changes under a file, or a base a variant's kind refuses, fails here."""
    from bench.objective_sweep import load_variants
    from train.config import load_config

    files = sorted((ROOT / "bench").glob("variants*.toml"))
    assert len(files) >= 4
    for path in files:
        for name, v in load_variants(path).items():
            load_config(v.get("config", "cpu-small"), v["set"])  # raises ConfigError on a bad key or value
    shading = load_variants(ROOT / "bench" / "variants_shading.toml")
    cfg = load_config("cpu-small", shading["default"]["set"])
    assert cfg.model.renderer == "net" and cfg.loss.w_dec == 10  # "default" = the previous defaults, pinned
    assert "model.kind=oracle" in shading["oracle"]["set"] and "model.renderer=net" not in shading["oracle"]["set"]
