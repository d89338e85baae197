"""`iae-eval report`: one self-contained HTML page (and Markdown) comparing runs.

Table 1 (FID/KID of R's images against real images), Table 3 (decomposition errors on a
PBR set), image grids with the same inputs across runs, and the training loss curves.
"""
from __future__ import annotations

import base64
import html
import io
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from blender_gen.conversions import linear_to_srgb, preview_srgb8  # noqa: E402
from blender_gen.dataset import INTRINSIC_LAYERS, atomic_write_bytes, atomic_write_json, open_dataset  # noqa: E402
from train.config import Config, config_from_dict  # noqa: E402

from .decomposition import score_predictions, write_results  # noqa: E402
from .fid import InceptionFeatures, extract, fid_from_features, kid_from_features  # noqa: E402
from .images import image_source  # noqa: E402


def run_label(cfg: Config) -> str:
    """How the paper's tables name a configuration."""
    if cfg.model.kind == "cyclegan":
        return "CycleGAN"
    if cfg.model.kind == "munit":
        return "MUNIT"
    parts = []
    if not cfg.loss.shared_discriminator:
        parts.append("w/o shared discr.")
    if not cfg.loss.decomposition_cycle:
        parts.append("w/o decomp. cycle")
    if not cfg.loss.rendering_cycle:
        parts.append("w/o rendering cycle")
    parts += [f"w/o {c}" for c in "ANF" if c not in cfg.model.inputs]
    return "Ours, " + ", ".join(parts) if parts else "Ours (full)"


def _png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode()


def loss_plot(stats: Path, title: str) -> bytes:
    rows = [json.loads(line) for line in stats.read_text().splitlines() if line.strip()]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
    steps = [r["step"] for r in rows]
    for ax, prefix in zip(axes, ("G/", "D/")):
        for key in sorted({k for r in rows for k in r if k.startswith(prefix)}):
            ax.plot(steps, [r.get(key, np.nan) for r in rows], label=key[2:], linewidth=1)
        ax.set_xlabel("step")
        ax.set_title(f"{title}: {'generators' if prefix == 'G/' else 'discriminators'}", fontsize=9)
        ax.legend(fontsize=6)
        ax.set_yscale("log")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def build_report(runs: list[Path], data: Path, real: Path, out: Path, intrinsics: Path | None = None,
                 limit: int = 50, grid: int = 4, inception: str | None = None, progress: bool = True) -> Path:
    from train.inference import decompose_images, render_dataset

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    feat = InceptionFeatures(inception)
    n_real, real_imgs = image_source(real, limit)
    real_feats = extract(feat, real_imgs, n_real, progress=progress, desc="real features")
    entries = []
    for k, run in enumerate(runs):
        opts = json.loads((Path(run) / "training_options.json").read_text())
        cfg = config_from_dict(opts["config"])
        label = run_label(cfg)
        slug = f"{k:02d}_{re.sub(r'[^A-Za-z0-9]+', '_', Path(run).name)}"
        rdir = out / "runs" / slug
        pred_dir = rdir / "predictions"
        if not (pred_dir / "dataset.json").exists() or not json.loads((pred_dir / "dataset.json").read_text()).get("complete"):
            import shutil

            shutil.rmtree(pred_dir, ignore_errors=True)
            decompose_images(run, data, pred_dir, limit=limit, progress=progress)
        rows, dec = score_predictions(data, pred_dir, progress=progress)
        write_results(rows, dec, rdir / "decomposition.json")
        intr = Path(intrinsics) if intrinsics else Path(opts["intrinsics"])
        rendered = render_dataset(run, intr, rdir / "rendered", limit=limit, progress=progress)
        n_fake, fake_imgs = image_source(rdir / "rendered")
        fake_feats = extract(feat, fake_imgs, n_fake, progress=progress, desc=f"{label} features")
        kid, kid_std = kid_from_features(real_feats, fake_feats)
        fidkid = {"fid": fid_from_features(real_feats, fake_feats), "kid": kid, "kid_std": kid_std,
                  "real_images": len(real_feats), "fake_images": len(fake_feats)}
        atomic_write_json(rdir / "fid.json", fidkid)
        stats = Path(run) / "stats.jsonl"
        curve = loss_plot(stats, label) if stats.exists() else None
        if curve:
            atomic_write_bytes(rdir / "losses.png", curve)
        entries.append({"run": str(run), "label": label, "slug": slug, "dec": dec, "fid": fidkid, "curve": curve,
                        "rendered": sorted(rendered)[:grid], "pred_dir": pred_dir, "intrinsics": intr,
                        "step": json.loads((pred_dir / "dataset.json").read_text())["step"]})
    page = _html(entries, data, real, grid)
    atomic_write_bytes(out / "report.html", page.encode())
    atomic_write_bytes(out / "report.md", _markdown(entries).encode())
    atomic_write_json(out / "results.json", [{k: e[k] for k in ("run", "label", "step", "dec", "fid")} for e in entries])
    return out / "report.html"


def _table1(entries) -> tuple[list[str], list[list[str]]]:
    head = ["Run", "Config", "Step", "FID", "KID x100", "KID (raw)", "images (real/fake)"]
    rows = [[Path(e["run"]).name, e["label"], str(e["step"]), f"{e['fid']['fid']:.2f}", f"{100 * e['fid']['kid']:.2f}",
             f"{e['fid']['kid']:.5f} ± {e['fid']['kid_std']:.5f}",
             f"{e['fid']['real_images']}/{e['fid']['fake_images']}"] for e in entries]
    return head, rows


def _table3(entries) -> tuple[list[str], list[list[str]]]:
    head = ["Run", "Config", "Normal mean (deg)", "Normal median", "< 11.25°", "< 22.5°", "< 30°",
            "Albedo L1 (0-255)", "Albedo si-L1 (lin.)", "Reflection L1 (0-255)", "samples"]
    rows = []
    for e in entries:
        d = e["dec"]
        rows.append([Path(e["run"]).name, e["label"], f"{d['normal_mean_deg']:.2f}", f"{d['normal_median_deg']:.2f}",
                     f"{d['normal_under_11.25_pct']:.1f}%", f"{d['normal_under_22.5_pct']:.1f}%",
                     f"{d['normal_under_30_pct']:.1f}%", f"{d['albedo_l1_srgb255']:.2f}",
                     f"{d['albedo_si_l1_linear']:.4f}", f"{d['reflection_l1_srgb255']:.2f}", str(d["samples"])])
    return head, rows


def _md_table(head, rows) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _markdown(entries) -> str:
    parts = ["# Intrinsic Autoencoder evaluation", "",
             "## Table 1: realism of R's images (FID and KID against real images; lower is better)", "",
             _md_table(*_table1(entries)), "",
             "## Table 3: decomposition errors against Cycles ground truth (lower is better, except the % columns)", "",
             _md_table(*_table3(entries)), "", "Pictures and loss curves: report.html; per-run files under runs/."]
    return "\n".join(parts) + "\n"


def _img(src: str, alt: str) -> str:
    return f'<img src="{src}" alt="{html.escape(alt)}">'


def _html(entries, data: Path, real: Path, grid: int) -> str:
    def table(head, rows):
        th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
        trs = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
        return f"<table><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>"

    # rendering grid: the same intrinsics inputs, then each run's image
    intr_ds = open_dataset(entries[0]["intrinsics"], kinds=("intrinsics", "pbr"))
    ren_rows = []
    for j in range(min(grid, len(intr_ds))):
        layers = intr_ds.load(j, INTRINSIC_LAYERS)
        cells = [_img(_data_uri(_png_bytes(preview_srgb8(k, layers[k]))), f"input {k}") for k in INTRINSIC_LAYERS]
        for e in entries:
            if j < len(e["rendered"]):
                cells.append(_img(_data_uri(Path(e["rendered"][j]).read_bytes()), f"{e['label']} render"))
        ren_rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    ren_head = "".join(f"<th>{h}</th>" for h in ["normal", "albedo", "reflection"] + [html.escape(e["label"]) for e in entries])

    # decomposition grid: image and ground truth, then each run's prediction
    gt_ds = open_dataset(data, kinds=("pbr",))
    preds = []
    for e in entries:
        ds = open_dataset(e["pred_dir"])
        preds.append((e, ds, {r["index"]: k for k, r in enumerate(ds.rows)}))
    dec_rows = []
    for j in range(min(grid, len(gt_ds))):
        gt = gt_ds.load(j)
        img = (linear_to_srgb(gt["rgb"]) * 255 + 0.5).astype(np.uint8)
        cells = [f"<th>image &amp; ground truth</th><td>{_img(_data_uri(_png_bytes(img)), 'input image')}</td>"]
        cells += [f"<td>{_img(_data_uri(_png_bytes(preview_srgb8(k, gt[k]))), 'ground truth ' + k)}</td>" for k in INTRINSIC_LAYERS]
        dec_rows.append("<tr>" + "".join(cells) + "</tr>")
        index = gt_ds.rows[j]["index"]
        for e, pred_ds, pos in preds:
            if index not in pos:
                continue
            pred = pred_ds.load(pos[index])
            cells = [f"<th>{html.escape(e['label'])}</th><td></td>"]
            cells += [f"<td>{_img(_data_uri(_png_bytes(preview_srgb8(k, pred[k]))), e['label'] + ' ' + k)}</td>"
                      for k in INTRINSIC_LAYERS]
            dec_rows.append("<tr>" + "".join(cells) + "</tr>")

    curves = "".join(f"<h3>{html.escape(e['label'])} ({html.escape(Path(e['run']).name)})</h3>"
                     + _img(_data_uri(e["curve"]), f"loss curves {e['label']}") for e in entries if e["curve"])
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Intrinsic Autoencoder evaluation</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 4px 8px; text-align: center; font-size: 13px; }}
td img {{ max-width: 256px; display: block; }}
h3 {{ margin-bottom: 0.2em; }}
</style>
<script>
window.__errors = [];
window.addEventListener("error", e => window.__errors.push(String(e.message || e.type)), true);
window.addEventListener("load", () => {{
  const imgs = Array.from(document.images);
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  const s = document.getElementById("selfcheck");
  s.textContent = `images=${{imgs.length}} broken=${{broken}} errors=${{window.__errors.length}}`;
}});
</script></head><body>
<h1>Intrinsic Autoencoder evaluation</h1>
<p>Decomposition data: <code>{html.escape(str(data))}</code>; real images: <code>{html.escape(str(real))}</code>.</p>
<h2>Table 1: realism of R's images (FID / KID against real images, lower is better)</h2>
{table(*_table1(entries))}
<h2>Table 3: decomposition errors against Cycles ground truth</h2>
<p>Normals: angle after normalising predictions; albedo and reflection: L1 on the 0-255 sRGB scale; albedo also
scale-invariant L1 on linear values. Lower is better except the % columns.</p>
{table(*_table3(entries))}
<h2>Deferred neural rendering: the same intrinsics through each run's R</h2>
<table><thead><tr>{ren_head}</tr></thead><tbody>{''.join(ren_rows)}</tbody></table>
<h2>Intrinsic decomposition: each run's H next to the ground truth</h2>
<table><thead><tr><th></th><th>image</th><th>normal</th><th>albedo</th><th>reflection</th></tr></thead>
<tbody>{''.join(dec_rows)}</tbody></table>
<h2>Training losses</h2>
{curves}
<p id="selfcheck">not loaded</p>
</body></html>
"""
