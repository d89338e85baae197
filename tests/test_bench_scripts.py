"""Every benchmark script (`make bench`, the sweeps) imports: a renamed function once broke one
silently, since no test runs the benchmarks themselves."""
from __future__ import annotations

import subprocess
import sys

from .conftest import ROOT, bench_module


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


def test_sanity_ab_takes_a_committed_curve_as_a_reference(tmp_path):
    """A probe-rows file (a sweep's curve, or one this script committed) joins the table beside run
    folders, its seed from the options committed beside it or else from its rows."""
    import json

    def row(step: int, deg: float) -> dict:
        r = {"step": step, "seed": 21, "probe/normal_deg": deg + 1, "probe_ema/normal_deg": deg,
             "probe/const_normal_deg": 40.0, "probe/prior_normal_deg": 35.0}
        for pre in ("probe/", "probe_ema/"):
            r.update({pre + "albedo_l1": 33.0, pre + "reflection_l1": 30.0, pre + "normal_hf_ratio": 2.0,
                      pre + "albedo_hf_ratio": 1.5, pre + "r_sensitivity": 0.8, pre + "r_colour_corr": 0.9,
                      **{f"{pre}normal_corr_{a}": 0.5 for a in "xyz"}})
        return r

    rows = tmp_path / "ref.jsonl"
    rows.write_text("".join(json.dumps(row(s, d)) + "\n" for s, d in ((250, 45.0), (500, 38.5), (750, 36.0))))
    out = tmp_path / "ab"
    proc = subprocess.run([sys.executable, "bench/sanity_ab.py", "--out", str(out), f"ref_s21={rows}"], cwd=ROOT,
                          capture_output=True, text=True, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| ref_s21 | 21 | 750 | 36.0 (37.0; 4.5) | 40.0 / 35.0 |" in (out / "table.md").read_text()
    assert (out / "curves.png").stat().st_size > 1000 and not (out / "ref_s21_probe.jsonl").exists()
    # --until: every run read up to one step (a run stopped early beside complete ones)
    until = subprocess.run([sys.executable, "bench/sanity_ab.py", "--out", str(out), "--until", "500", "--ylim", "20", "40",
                            f"ref_s21={rows}"],
                           cwd=ROOT, capture_output=True, text=True, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert until.returncode == 0, until.stderr[-2000:]
    assert "| ref_s21 | 21 | 500 | 38.5 (" in (out / "table.md").read_text()
    # a file this script committed (LABEL_probe.jsonl, rows without seeds): its seed from the options beside it
    committed = tmp_path / "full_probe.jsonl"
    committed.write_text("".join(json.dumps({k: v for k, v in row(s, d).items() if k != "seed"}) + "\n"
                                 for s, d in ((250, 45.0), (500, 38.5))))
    (tmp_path / "full_training_options.json").write_text(json.dumps({"config": {"run": {"seed": 22}}}))
    redraw = subprocess.run([sys.executable, "bench/sanity_ab.py", "--out", str(out), f"full={committed}"],
                            cwd=ROOT, capture_output=True, text=True, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert redraw.returncode == 0, redraw.stderr[-2000:]
    assert "| full | 22 | 500 | 38.5 (" in (out / "table.md").read_text()
    bad = subprocess.run([sys.executable, "bench/sanity_ab.py", "--out", str(out), f"x={tmp_path / 'none'}"],
                         cwd=ROOT, capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert bad.returncode != 0 and "expected LABEL=RUN_DIR" in bad.stderr


def test_sanity_ab_names_a_curve_that_leaves_the_plotted_range():
    """With --ylim an untrained ablation's curve leaves the plot; its legend entry says where it ends."""
    legend_label = bench_module("sanity_ab").legend_label
    assert legend_label("full", [36.0, 25.0], (20.0, 45.0)) == "full"
    assert legend_label("full", [36.0, 25.0], None) == "full"
    assert legend_label("no_N", [78.8, 79.2], (20.0, 45.0)) == "no_N (off the scale: ends at 79°)"
    assert legend_label("no_ren", [60.0, 30.0], (20.0, 45.0)).endswith("ends at 30°)")  # left it, came back


def test_lattice_peaks_find_a_checkerboard_and_not_a_smooth_map():
    """bench/lattice_peaks.py's figure: about 1 on a map without a lattice pattern, far above with one."""
    import torch

    lattice_peak_ratio = bench_module("lattice_peaks").lattice_peak_ratio
    torch.manual_seed(0)
    smooth = torch.nn.functional.avg_pool2d(torch.randn(8, 3, 68, 132), 5, stride=1)  # (8, 3, 64, 128)
    yy, xx = torch.meshgrid(torch.arange(64), torch.arange(128), indexing="ij")
    lattice = ((yy % 4 == 0) & (xx % 4 == 0)).float() * smooth.std()  # a dot every 4 pixels
    assert 0.5 < lattice_peak_ratio(smooth, 4) < 2
    assert lattice_peak_ratio(smooth + lattice, 4) > 10


def test_h_upsample_speed_times_the_three_layers_and_counts_their_parameters(tmp_path):
    """bench/h_upsample_speed.py: one row per upsampling kind; resize keeps the transposed layer's
    parameter count, subpixel's four phases add to it; a malformed --size is refused by name."""
    import json

    out = tmp_path / "speed.json"
    proc = subprocess.run([sys.executable, "bench/h_upsample_speed.py", "--size", "16x32", "--batch", "1",
                           "--rounds", "1", "--repeats", "1", "--json", str(out)], cwd=ROOT,
                          capture_output=True, text=True, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r["upsample"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"transposed", "resize", "subpixel"}
    assert rows["resize"]["params"] == rows["transposed"]["params"] < rows["subpixel"]["params"]
    assert all(r["ms"] > 0 for r in rows.values()) and rows["transposed"]["relative"] == 1.0
    assert proc.stdout.count("\n| ") == 4  # the header and three rows
    bad = subprocess.run([sys.executable, "bench/h_upsample_speed.py", "--size", "64"], cwd=ROOT,
                         capture_output=True, text=True)
    assert bad.returncode != 0 and "--size" in bad.stderr
