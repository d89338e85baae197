"""`iae-eval report`: one self-contained HTML page (and Markdown) comparing runs.

Table 1 (FID/KID of R's images against real images), Table 3 (decomposition errors on a
PBR set), image grids with the same inputs across runs, and the training loss curves.
"""
from __future__ import annotations

import base64
import html
import io
import json
import os
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from blender_gen.conversions import linear_to_srgb, preview_srgb8  # noqa: E402
from blender_gen.dataset import (INTRINSIC_LAYERS, atomic_write_bytes, atomic_write_json, open_dataset,  # noqa: E402
                                 save_png, sha256_file)
from train.config import Config  # noqa: E402
from train.probe import probe_plot  # noqa: E402
from train.run_folder import RunFolder  # noqa: E402

from .decomposition import score_predictions, write_results  # noqa: E402
from .fid import FID_MIN_IMAGES, InceptionFeatures, compare_sets, extract, kid_text  # noqa: E402
from .images import image_source  # noqa: E402
from .paper_figures import PAPER_TABLE1, PAPER_TABLE3  # noqa: E402


def run_label(cfg: Config) -> str:
    """How the paper's tables name a configuration."""
    if cfg.model.kind == "cyclegan":
        return "CycleGAN"
    if cfg.model.kind == "munit":
        return "MUNIT"
    if cfg.model.kind == "oracle":
        return "Supervised oracle (paired PBR)"
    parts = []
    if not cfg.loss.shared_discriminator:
        parts.append("w/o shared discr.")
    if not cfg.loss.decomposition_cycle:
        parts.append("w/o decomp. cycle")
    if not cfg.loss.rendering_cycle:
        parts.append("w/o rendering cycle")
    parts += [f"w/o {c}" for c in "ANF" if c not in cfg.model.inputs]
    label = "Ours, " + ", ".join(parts) if parts else "Ours (full)"
    changed = objective_changes(cfg)
    if changed:  # a run trained with --set on its objective is not the paper's row of that name
        label += ", " + ", ".join(changed[:3]) + (f" (+{len(changed) - 3} more)" if len(changed) > 3 else "")
    return label


# the ablation switches the label already names
_NAMED = ("loss.shared_discriminator", "loss.decomposition_cycle", "loss.rendering_cycle")


def objective_changes(cfg: Config) -> list[str]:
    """The objective settings (`key=value`) in which a run differs from the nearer of the two objectives
    `reproduce` trains (the measured defaults and the paper's), e.g. ["loss.w_chroma=0.0"]."""
    from train.config import load_config, objective_differences

    have = cfg.to_dict()
    best: list[str] | None = None
    for ref in (Config(), load_config("paper")):
        keys = [k for k in objective_differences(cfg, ref) if k not in _NAMED]
        keys.sort(key=lambda k: not k.startswith("loss."))  # the loss settings first, then R's
        diff = [f"{k}={have[k.split('.')[0]][k.split('.')[1]]}" for k in keys]
        if best is None or len(diff) < len(best):
            best = diff
    return best or []


def _png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def _data_uri(png: bytes, mime: str = "image/png") -> str:
    return f"data:{mime};base64," + base64.b64encode(png).decode()


def read_reference(path: Path) -> tuple[bytes, str]:
    """A picture to show beside the report's own (`--reference`): its bytes and MIME type, checked
    before any evaluation work."""
    try:
        data = Path(path).read_bytes()  # read once: the bytes checked are the bytes shown
        with Image.open(io.BytesIO(data)) as im:
            fmt = im.format
            im.verify()
    except Exception as exc:  # PIL raises OSError, SyntaxError and others for broken files
        raise ValueError(f"--reference {path}: not a readable image ({exc})") from None
    if fmt not in ("PNG", "JPEG"):
        raise ValueError(f"--reference {path}: a {fmt} image; expected PNG or JPEG")
    return data, "image/png" if fmt == "PNG" else "image/jpeg"


def loss_plot(rows: list[dict], title: str) -> bytes:
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




def _cache_key(run: Path, checkpoint: Path, cfg, data: Path, limit: int | None) -> dict:
    """What cached predictions depend on: the checkpoint's content (not its path or step: a run
    retrained in place to the same step is another model), the resolved config, the data set and
    its content, the limit."""
    info = open_dataset(data).info
    return {"run": str(Path(run).resolve()), "checkpoint_sha256": sha256_file(checkpoint),
            "config": cfg.to_dict(), "data": str(Path(data).resolve()),
            "data_recipe": info.get("recipe"), "data_count": info.get("count"), "limit": limit}


# what results.json records per run: which weights (one checkpoint file for every figure), trained how
RESULT_RUN_FIELDS = ("run", "label", "step", "checkpoint", "checkpoint_sha256", "seed", "size", "trained_on", "slug",
                     "dec", "fid")


def _gallery(run: Path, photos: Path, folder: Path, checkpoint: Path, progress: bool, warnings: list[str]) -> list[Path]:
    """The run's H on the gallery photos (train.photos panels), one per photo in name order."""
    import shutil

    from train.inference import PhotosSkipped, decompose_images

    shutil.rmtree(folder, ignore_errors=True)
    try:
        decompose_images(run, photos, folder, progress=progress, checkpoint=checkpoint)
    except PhotosSkipped as exc:
        if f"gallery: {exc}" not in warnings:
            warnings.append(f"gallery: {exc}")
    return sorted(p for p in (folder / "photos").glob("*.png") if not p.stem.endswith(
        ("_normal", "_albedo", "_reflection", "_render")))


def pin_checkpoint(run: Path, folder: Path) -> tuple[Path, int]:
    """The run's newest readable checkpoint, linked (or copied) into `folder`: every figure of the
    report comes from this one file, even while the run trains on and prunes its checkpoints."""
    import shutil

    from train.inference import load_run_checkpoint

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for _ in range(5):  # the trainer may prune the newest-but-one between finding and linking it
        _, _, step, checkpoint = load_run_checkpoint(run)
        pinned = folder / checkpoint.name
        try:
            for src, dst in ((checkpoint.with_suffix(".json"), pinned.with_suffix(".json")), (checkpoint, pinned)):
                try:
                    os.link(src, dst)
                except OSError as exc:
                    if isinstance(exc, FileNotFoundError):
                        raise
                    shutil.copyfile(src, dst)
            return pinned, step
        except FileNotFoundError:
            for f in folder.iterdir():
                f.unlink()
    raise OSError(f"--run {run}: its checkpoints changed five times while the report pinned one; retry")


def _cached_predictions(run: Path, checkpoint: Path, data: Path, pred_dir: Path, limit: int | None,
                        progress: bool) -> int:
    """Decompose `data` with `checkpoint` into `pred_dir` unless predictions for exactly this key
    are there; returns the step."""
    import shutil

    from train.inference import decompose_images, load_run_checkpoint

    cfg, _, step, checkpoint = load_run_checkpoint(run, checkpoint=checkpoint)
    key = _cache_key(run, checkpoint, cfg, data, limit)
    info_path = pred_dir / "dataset.json"
    if info_path.exists():
        info = json.loads(info_path.read_text())
        if info.get("complete") and info.get("cache_key") == key:
            return step
    shutil.rmtree(pred_dir, ignore_errors=True)
    decompose_images(run, data, pred_dir, limit=limit, progress=progress, checkpoint=checkpoint)
    info = json.loads(info_path.read_text())
    atomic_write_json(info_path, {**info, "cache_key": {**key, "step": info["step"]}})
    return info["step"]


def _reference_entries(train_intrinsics: Path, data: Path, real: Path, intrinsics: Path, out: Path,
                       size: tuple[int, int], limit: int | None, grid: int, feat, real_features,
                       progress: bool) -> list[dict]:
    """The constant predictor and the per-pixel prior (Table 3) and the albedo-copy renderer
    (Table 1), on the same sets."""
    import shutil

    from .reference_rows import albedo_images, constant_predictions, prior_predictions

    rdir = out / "runs" / "reference"
    shutil.rmtree(rdir, ignore_errors=True)
    pred_dir = constant_predictions(train_intrinsics, data, rdir / "constant", progress=progress)
    rows, dec = score_predictions(data, pred_dir, limit=limit, progress=progress)
    write_results(rows, dec, rdir / "constant.json")
    prior_dir = prior_predictions(train_intrinsics, data, rdir / "prior", progress=progress)
    rows, prior_dec = score_predictions(data, prior_dir, limit=limit, progress=progress)
    write_results(rows, prior_dec, rdir / "prior.json")
    copies = albedo_images(intrinsics, rdir / "albedo", limit=limit, progress=progress)
    fidkid = compare_sets(real, copies, size, limit, model=feat, real_features=real_features, progress=progress)
    base = {"run": "-", "step": "-", "curve": None, "reference": True}
    return [{**base, "label": "Constant predictor", "slug": "constant", "dec": dec, "fid": None, "rendered": [],
             "pred_dir": pred_dir},
            {**base, "label": PRIOR, "slug": "prior", "dec": prior_dec, "fid": None, "rendered": [],
             "pred_dir": prior_dir},
            {**base, "label": "Albedo copy (no renderer)", "slug": "albedo", "dec": None, "fid": fidkid,
             "rendered": sorted(copies.glob("*.png"))[:grid], "pred_dir": None}]


def build_report(runs: list[Path], data: Path, real: Path, out: Path, intrinsics: Path, limit: int | None = None,
                 grid: int = 4, inception: str | None = None, progress: bool = True,
                 references: bool = True, gallery: Path | None = None,
                 reference: tuple[Path, str] | None = None) -> Path:
    """Evaluate every run on the same sets and write report.html, report.md and results.json.

    Refuses sets that overlap against the protocol (eval.protocol); FID/KID fakes are R's
    renders of `intrinsics`, which must be a set the runs never trained on. `reference`: a picture
    and its caption shown after the report's own decompositions (e.g. a trained model's, beside a
    short run's).
    """
    import shutil

    from train.inference import load_run_options, render_dataset
    from .protocol import check_sets, describe

    out = Path(out)
    ref = (*read_reference(reference[0]), reference[1]) if reference else None
    runs_opts = [(Path(run), *load_run_options(run)) for run in runs]  # a dataset folder given as a run fails here
    sets = {"eval": describe("--data", data), "real": describe("--real", real), "fid": describe("--intrinsics", intrinsics)}
    warnings: list[str] = []
    trained_on = {}  # run -> content digests of its two training sets (`seeds` refuses a training counted twice)
    for run, opts, _ in runs_opts:
        train_set = describe(f"{run.name} training intrinsics", opts["intrinsics"])
        train_real = describe(f"{run.name} real images", opts["real"])
        trained_on[run] = [train_set.identity.get("manifest_sha256"), train_real.identity.get("manifest_sha256")]
        sets.setdefault(f"train:{train_set.path}", train_set)
        sets.setdefault(f"trainreal:{train_real.path}", train_real)
        for w in check_sets(train_set, train_real, sets["eval"], sets["fid"]):
            if w not in warnings:
                warnings.append(w)
    out.mkdir(parents=True, exist_ok=True)
    slugs = [f"{k:02d}_{re.sub(r'[^A-Za-z0-9]+', '_', run.name)}" for k, (run, _, _) in enumerate(runs_opts)]
    for stale in (out / "runs").glob("[0-9][0-9]_*"):  # an earlier report's runs must not pass for these
        if stale.name not in slugs:
            shutil.rmtree(stale)
    feat = InceptionFeatures(inception)
    real_feats: dict[tuple[int, int], np.ndarray] = {}
    entries = []
    for k, (run, opts, cfg) in enumerate(runs_opts):
        label, slug = run_label(cfg), slugs[k]
        rdir = out / "runs" / slug
        pred_dir = rdir / "predictions"
        checkpoint, step = pin_checkpoint(run, rdir / "checkpoint")
        _cached_predictions(run, checkpoint, data, pred_dir, limit, progress)
        rows, dec = score_predictions(data, pred_dir, limit=limit, progress=progress)
        write_results(rows, dec, rdir / "decomposition.json")
        shutil.rmtree(rdir / "rendered", ignore_errors=True)  # always this step's renders, never a stale mix
        rendered = render_dataset(run, intrinsics, rdir / "rendered", limit=limit, progress=progress,
                                  checkpoint=checkpoint)
        size = (cfg.data.height, cfg.data.width)
        if size not in real_feats:
            n_real, real_imgs = image_source(real, size, limit)
            real_feats[size] = extract(feat, real_imgs, n_real, progress=progress, desc=f"real features {size}")
        fidkid = compare_sets(real, rdir / "rendered", size, limit, model=feat, real_features=real_feats[size],
                              progress=progress)
        atomic_write_json(rdir / "fid.json", fidkid)
        stats = RunFolder(run).stats()
        curve = loss_plot(stats, label) if stats else None
        if curve:
            atomic_write_bytes(rdir / "losses.png", curve)
        probe_curve = probe_plot(stats, label)  # None for a run trained without --probe
        if probe_curve:
            atomic_write_bytes(rdir / "probe.png", probe_curve)
        panels = _gallery(run, gallery, rdir / "gallery", checkpoint, progress, warnings) if gallery else []
        digest = sha256_file(checkpoint)
        shutil.rmtree(rdir / "checkpoint")  # its name and digest are recorded; the run keeps the file
        entries.append({"run": str(run), "label": label, "slug": slug, "dec": dec, "fid": fidkid, "curve": curve,
                        "checkpoint": checkpoint.name, "checkpoint_sha256": digest, "seed": cfg.run.seed,
                        "size": [cfg.data.height, cfg.data.width], "trained_on": trained_on[run],
                        "probe_curve": probe_curve, "gallery": panels,
                        "rendered": sorted(rendered)[:grid], "pred_dir": pred_dir, "step": step})
    _name_runs(entries)
    if references:
        run, opts, cfg = runs_opts[0]
        size = (cfg.data.height, cfg.data.width)
        entries += _reference_entries(Path(opts["intrinsics"]), data, real, Path(intrinsics), out, size, limit, grid,
                                      feat, real_feats[size], progress)
    datasets = [v.summary() for v in sets.values()]
    save_png(out / "render_grid.png", render_grid_png(entries, Path(intrinsics), grid))
    tiles = decomposition_tiles(entries, Path(data), grid)
    save_png(out / "decomposition_grid.png", decomposition_grid_png(tiles))
    ref_name = None
    if ref is not None:
        ref_name = "reference" + (".png" if ref[1] == "image/png" else ".jpg")
        atomic_write_bytes(out / ref_name, ref[0])
    page = _html(entries, tiles, data, real, Path(intrinsics), grid, datasets, warnings, ref)
    atomic_write_bytes(out / "report.html", page.encode())
    atomic_write_bytes(out / "report.md", _markdown(entries, datasets, warnings, ref and (ref_name, ref[2])).encode())
    atomic_write_json(out / "results.json", {"runs": [{k: e[k] for k in RESULT_RUN_FIELDS}
                                                      for e in entries if not e.get("reference")],
                                             "references": [{k: e[k] for k in ("label", "dec", "fid")}
                                                            for e in entries if e.get("reference")],
                                             "datasets": datasets, "warnings": warnings})
    return out / "report.html"


def run_names(runs: list[str]) -> list[str]:
    """Each run's folder name, with as many parent folders as it takes to tell it apart from the
    other runs (two seeds' runs are often both called `full`)."""
    parts = [Path(r).parts or (str(r),) for r in runs]

    def suffix(p: tuple[str, ...], depth: int) -> str:
        return "/".join(p[-depth:])

    names = []
    for i, p in enumerate(parts):
        depth = 1
        while depth < len(p) and any(suffix(p, depth) == suffix(q, depth) for j, q in enumerate(parts) if j != i):
            depth += 1
        names.append(suffix(p, depth))
    return names


def _name_runs(entries: list[dict]) -> None:
    """Give each run entry its table name and, where two runs share a configuration label, a
    column title that tells them apart in the grids."""
    names = run_names([e["run"] for e in entries])
    labels = [e["label"] for e in entries]
    for e, name in zip(entries, names):
        e["name"] = name
        e["title"] = e["label"] if labels.count(e["label"]) == 1 else f"{e['label']}, {name}"


def render_grid_png(entries, intrinsics: Path, grid: int, tile: tuple[int, int] = (256, 128)) -> np.ndarray:
    """One picture for people: per row the same unseen intrinsics (normal, albedo, reflection),
    then every run's render of them, each column labelled."""
    from PIL import ImageDraw

    renderers = [e for e in entries if e["rendered"]]
    ds = open_dataset(intrinsics, kinds=("intrinsics", "pbr"))
    w, h = tile
    labels = ["normal", "albedo", "reflection"] + [e.get("title", e["label"]) for e in renderers]
    n = min(grid, len(ds))
    sheet = Image.new("RGB", (w * len(labels), 18 + h * n), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c, text in enumerate(labels):
        draw.text((c * w + 4, 3), text[:40], fill=(0, 0, 0))
    for j in range(n):
        layers = ds.load(j, INTRINSIC_LAYERS)
        tiles = [Image.fromarray(preview_srgb8(k, layers[k])) for k in INTRINSIC_LAYERS]
        tiles += [Image.open(e["rendered"][j]).convert("RGB") if j < len(e["rendered"]) else Image.new("RGB", tile)
                  for e in renderers]
        for c, t in enumerate(tiles):
            sheet.paste(t.resize(tile, Image.Resampling.BILINEAR), (c * w, 18 + j * h))
    return np.asarray(sheet)


def merged_grids(parts: list[Path], rows: int = 4, tile: tuple[int, int] = (256, 128)) -> tuple[np.ndarray, np.ndarray]:
    """The pictures of one report drawn from several (the parts of one seed, `iae-eval merge`):
    R's renders of the same unseen intrinsics by every run, then each run's decomposition of the
    same Table-3 images (image, ground truth, then one column per run; a row per layer).

    Needs the parts' report folders (their runs/NN_name/rendered and predictions), and the
    --intrinsics and --data sets they name on this machine.
    """
    from .seeds import read_results

    folders = [Path(p).parent if Path(p).name == "results.json" else Path(p) for p in parts]
    entries, sets = [], {}
    for folder in folders:
        data = read_results(folder)
        for d in data.get("datasets", []):
            sets.setdefault(d.get("role"), Path(d["path"]))
        for k, run in enumerate(data.get("runs", [])):
            # the folder the report recorded (older reports: the only NN_* folder of that index)
            found = [folder / "runs" / run["slug"]] if run.get("slug") else sorted((folder / "runs").glob(f"{k:02d}_*"))
            if len(found) > 1:
                raise ValueError(f"{folder / 'runs'}/{k:02d}_*: several folders for run '{run['label']}' and no record "
                                 "of which is its; rerun `iae-eval report` into a fresh --out")
            if not found or not (found[0] / "rendered").is_dir() or not (found[0] / "predictions").is_dir():
                raise ValueError(f"{folder / 'runs'}/{k:02d}_*: no rendered/ and predictions/ of run '{run['label']}'; "
                                 "the grids need the parts' report folders, not only their results.json")
            entries.append({"label": run["label"], "rendered": sorted((found[0] / "rendered").glob("*.png"))[:rows],
                            "pred_dir": found[0] / "predictions"})
    copies = folders[0] / "runs" / "reference" / "albedo"
    if copies.is_dir():
        entries.append({"label": "Albedo copy (no renderer)", "rendered": sorted(copies.glob("*.png"))[:rows],
                        "pred_dir": None})
    for role in ("--intrinsics", "--data"):
        if role not in sets or not sets[role].is_dir():
            raise ValueError(f"{folders[0] / 'results.json'}: its {role} set "
                             f"{sets.get(role, '(not named)')} is not on this machine; the grids draw its images")
    renders = render_grid_png(entries, sets["--intrinsics"], rows, tile)
    return renders, decomposition_grid_png(decomposition_tiles(entries, sets["--data"], rows), tile)


def decomposition_tiles(entries, data: Path, rows: int) -> dict:
    """The decomposition grid's content, loaded once for the HTML page and the PNG: per Table-3
    image its sRGB picture, its ground truth and every predicting run's layers (None where a run
    has no prediction of that image)."""
    gt_ds = open_dataset(data, kinds=("pbr",))
    preds = []
    for e in entries:
        if e["pred_dir"] is not None:
            ds = open_dataset(e["pred_dir"])
            preds.append((ds, {r["index"]: k for k, r in enumerate(ds.rows)}))
    images = []
    for j in range(min(rows, len(gt_ds))):
        gt = gt_ds.load(j)
        index = gt_ds.rows[j]["index"]
        images.append({"image": (linear_to_srgb(gt["rgb"]) * 255 + 0.5).astype(np.uint8),
                       "truth": {k: gt[k] for k in INTRINSIC_LAYERS},
                       "predictions": [ds.load(pos[index]) if index in pos else None for ds, pos in preds]})
    return {"labels": [e.get("title", e["label"]) for e in entries if e["pred_dir"] is not None], "images": images}


def decomposition_grid_png(tiles: dict, tile: tuple[int, int] = (256, 128)) -> np.ndarray:
    """Per Table-3 image three rows (normal, albedo, reflection): the image, the ground truth, then
    every run's prediction of that layer, each column labelled (`tiles` from decomposition_tiles)."""
    from PIL import ImageDraw

    w, h = tile
    labels = ["image", "ground truth"] + tiles["labels"]
    n = len(tiles["images"])
    sheet = Image.new("RGB", (w * len(labels), 18 + h * 3 * n), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for c, text in enumerate(labels):
        draw.text((c * w + 4, 3), text[:40], fill=(0, 0, 0))
    for j, item in enumerate(tiles["images"]):
        sheet.paste(Image.fromarray(item["image"]).resize(tile, Image.Resampling.BILINEAR), (0, 18 + 3 * j * h))
        for r, layer in enumerate(INTRINSIC_LAYERS):
            y = 18 + (3 * j + r) * h
            cells = [item["truth"][layer]] + [p[layer] if p is not None else None for p in item["predictions"]]
            for c, arr in enumerate(cells, start=1):
                t = Image.fromarray(preview_srgb8(layer, arr)) if arr is not None else Image.new("RGB", tile)
                sheet.paste(t.resize(tile, Image.Resampling.BILINEAR), (c * w, y))
            draw.text((w + 4, y + 3), layer, fill=(255, 255, 255))
    return np.asarray(sheet)


def _table1(entries) -> tuple[list[str], list[list[str]]]:
    head = ["Run", "Config", "Step", "FID", "KID x100", "KID (raw)", "images (real/fake)", "paper FID / KID x100"]
    rows = []
    for e in entries:
        f = e["fid"]
        if f is None:
            continue
        paper = PAPER_TABLE1.get(e["label"])
        fid = f"{f['fid']:.2f}" + (" (biased: < %d images)" % f["fid_min_images"] if f["fid_biased"] else "")
        rows.append([e.get("name", Path(e["run"]).name), e["label"], str(e["step"]), fid, f"{100 * f['kid']:.2f}",
                     kid_text(f), f"{f['real_images']}/{f['fake_images']}",
                     f"{paper[0]:.1f} / {paper[1]:.1f}" if paper else "-"])
    return head, rows


def _table3(entries) -> tuple[list[str], list[list[str]]]:
    head = ["Run", "Config", "Normal mean (deg)", "Normal median", "< 11.25°", "< 22.5°", "< 30°",
            "Albedo L1 (0-255)", "Albedo si-L1 (lin.)", "Reflection L1 (0-255)", "samples",
            "speckle N / A (x truth)", "gap closed N / A / F", "paper normal / albedo / reflection"]
    rows = []
    for e in entries:
        d = e["dec"]
        if d is None:
            continue
        paper = PAPER_TABLE3.get(e["label"])
        rows.append([e.get("name", Path(e["run"]).name), e["label"], f"{d['normal_mean_deg']:.2f}", f"{d['normal_median_deg']:.2f}",
                     f"{d['normal_under_11.25_pct']:.1f}%", f"{d['normal_under_22.5_pct']:.1f}%",
                     f"{d['normal_under_30_pct']:.1f}%", f"{d['albedo_l1_srgb255']:.2f}",
                     f"{d['albedo_si_l1_linear']:.4f}", f"{d['reflection_l1_srgb255']:.2f}",
                     f"{d['samples']} of {d.get('expected', d['samples'])}",
                     (f"{d['normal_hf_ratio']:.2f} / {d['albedo_hf_ratio']:.2f}" if "normal_hf_ratio" in d else "-"),
                     _gap_closed(d, entries),
                     f"{paper[0]:.2f}° / {paper[1]:.2f} / {paper[2]:.2f}" if paper else "-"])
    return head, rows


PRIOR = "Per-pixel prior (no image)"
TABLE3_NOTE = ("Normals: angle after normalising predictions; albedo and reflection: L1 on the 0-255 sRGB scale; albedo "
               "also scale-invariant L1 on linear values. Lower is better except the % columns. Two rows use no image: "
               "the constant predictor (every normal toward the camera, the training intrinsics' mean albedo and "
               "reflection) and the per-pixel prior (at each pixel the training intrinsics' mean normal, albedo and "
               "reflection); 'gap closed' is measured from the stronger of the two on each column to the supervised "
               "oracle (0 = no better than not looking at the image). Speckle: the high-frequency energy (mean "
               "|Laplacian| inside the car) of the predicted normals and albedo over the ground truth's (1 = as "
               "smooth as the truth), at the set's resolution: H's maps, resized up to it, are smoothed by the resize, so the training probe's figure (at the size H saw) is the one to compare runs by. Each run's H decomposes the images at its training size (moving-average "
               "weights where the run has them); its maps are resized bilinearly to the set's resolution.")
GAP_METRICS = ("normal_mean_deg", "albedo_l1_srgb255", "reflection_l1_srgb255")


def _gap_closed(d: dict, entries) -> str:
    """Per metric, the fraction of the gap between the stronger no-image reference (constant predictor
    or per-pixel prior, whichever is better on that metric) and the oracle that a run closes (1 = as
    good as the oracle, 0 = no better than a predictor that never looks at the image)."""
    ref = {e["label"]: e["dec"] for e in entries if e["dec"] is not None}
    bars = [ref[k] for k in ("Constant predictor", PRIOR) if k in ref]
    oracle = ref.get("Supervised oracle (paired PBR)")
    if not bars or oracle is None:
        return "-"
    parts = []
    for k in GAP_METRICS:
        bar = min(b[k] for b in bars)
        gap = bar - oracle[k]
        # no gap to close where the oracle is no better than the bar (a toy-size run)
        parts.append(f"{(bar - d[k]) / gap:.2f}" if gap > 1e-9 else "-")
    return " / ".join(parts)


def _datasets_table(datasets: list[dict]) -> tuple[list[str], list[list[str]]]:
    head = ["Role", "Path", "Kind", "Images", "Seed", "Cars", "Environments", "Car's share of the frame"]

    def names(c: dict) -> str:
        return f"{len(c)}: " + ", ".join(sorted(c)[:6]) + (" ..." if len(c) > 6 else "") if c else "-"

    rows = [[d["role"], d["path"], d["kind"], str(d["count"]), "-" if d["seed"] is None else str(d["seed"]),
             names(d["cars"]), names(d["envmaps"]), d.get("framing", "-")] for d in datasets]
    return head, rows


def _md_table(head, rows) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _markdown(entries, datasets, warnings, reference: tuple[str, str] | None = None) -> str:
    parts = ["# Intrinsic Autoencoder evaluation", "",
             "## Table 1: realism of R's images (FID and KID against real images; lower is better)", "",
             _md_table(*_table1(entries)), "",
             f"FID from fewer than {FID_MIN_IMAGES} images per set is biased upwards and marked so; KID is unbiased, "
             "so small comparisons should lean on it. The paper's figures (Table 1, 256x512, 16,000 real photos, "
             "full training) are printed for reference, not as a like-for-like comparison.", "",
             "## Table 3: decomposition errors against Cycles ground truth (lower is better, except the % columns)", "",
             _md_table(*_table3(entries)), "", TABLE3_NOTE, "",
             "## Data sets", "", _md_table(*_datasets_table(datasets)), ""]
    parts += [f"> WARNING: {w}" for w in warnings]
    if any(e.get("gallery") for e in entries):
        parts += ["", "## Your photos", "", "Each run's H on photos held out of training (photo, normal, albedo, "
                  "reflection, R(H(photo))): report.html, and runs/NN_name/gallery/photos/."]
    if reference:
        parts += ["", "## For comparison", "", f"![{reference[1]}]({reference[0]})", "", f"*{reference[1]}*"]
    parts += ["", "Pictures and loss curves: report.html; per-run files under runs/."]
    return "\n".join(parts) + "\n"


def _img(src: str, alt: str) -> str:
    return f'<img src="{src}" alt="{html.escape(alt)}">'


def _html(entries, tiles: dict, data: Path, real: Path, intrinsics: Path, grid: int, datasets: list[dict],
          warnings: list[str], reference: tuple[bytes, str, str] | None = None) -> str:
    def table(head, rows):
        th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
        trs = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
        return f"<table><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>"

    # rendering grid: the same intrinsics inputs, then each run's image
    intr_ds = open_dataset(intrinsics, kinds=("intrinsics", "pbr"))
    renderers = [e for e in entries if e["rendered"]]
    ren_rows = []
    for j in range(min(grid, len(intr_ds))):
        layers = intr_ds.load(j, INTRINSIC_LAYERS)
        cells = [_img(_data_uri(_png_bytes(preview_srgb8(k, layers[k]))), f"input {k}") for k in INTRINSIC_LAYERS]
        for e in renderers:
            if j < len(e["rendered"]):
                cells.append(_img(_data_uri(Path(e["rendered"][j]).read_bytes()), f"{e['label']} render"))
        ren_rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    ren_head = "".join(f"<th>{h}</th>" for h in ["normal", "albedo", "reflection"] + [html.escape(e.get("title", e["label"])) for e in renderers])

    # decomposition grid: image and ground truth, then each run's prediction
    dec_rows = []
    for item in tiles["images"]:
        cells = [f"<th>image &amp; ground truth</th><td>{_img(_data_uri(_png_bytes(item['image'])), 'input image')}</td>"]
        cells += [f"<td>{_img(_data_uri(_png_bytes(preview_srgb8(k, item['truth'][k]))), 'ground truth ' + k)}</td>"
                  for k in INTRINSIC_LAYERS]
        dec_rows.append("<tr>" + "".join(cells) + "</tr>")
        for label, pred in zip(tiles["labels"], item["predictions"]):
            if pred is None:
                continue
            cells = [f"<th>{html.escape(label)}</th><td></td>"]
            cells += [f"<td>{_img(_data_uri(_png_bytes(preview_srgb8(k, pred[k]))), label + ' ' + k)}</td>"
                      for k in INTRINSIC_LAYERS]
            dec_rows.append("<tr>" + "".join(cells) + "</tr>")

    # the gallery: photos no run trained on, each run's H and R(H(photo)) beside the photo
    galleries = [e for e in entries if e.get("gallery")]
    gallery_html = ""
    if galleries:
        blocks = []
        for e in galleries:
            figs = "".join(f'<figure>{_img(_data_uri(p.read_bytes()), e["label"] + " " + p.stem)}'
                           f"<figcaption>{html.escape(p.stem)}</figcaption></figure>" for p in e["gallery"])
            blocks.append(f"<h3>{html.escape(e['label'])}</h3>{figs}")
        gallery_html = ("<h2>Your photos: each run's decomposition of photos held out of training</h2>"
                        "<p>Per photo: the photo, H's normal, albedo and reflection at the photo's size, and "
                        "R(H(photo)). Files: runs/NN_name/gallery/photos/.</p>" + "".join(blocks))
    warn_html = "".join(f'<p class="warning">WARNING: {html.escape(w)}</p>' for w in warnings)
    reference_html = ""
    if reference is not None:
        data_bytes, mime, caption = reference
        reference_html = ("<h2>For comparison</h2><figure>" + _img(_data_uri(data_bytes, mime), caption)
                          + f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    curves = "".join(f"<h3>{html.escape(e['label'])} ({html.escape(e.get('name', Path(e['run']).name))})</h3>"
                     + _img(_data_uri(e["curve"]), f"loss curves {e['label']}")
                     + (_img(_data_uri(e["probe_curve"]), f"probe curves {e['label']}") if e.get("probe_curve") else "")
                     for e in entries if e["curve"])
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Intrinsic Autoencoder evaluation</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 4px 8px; text-align: center; font-size: 13px; }}
/* training-size renders shown as large as the inputs, smaller where many runs share the width */
td img {{ width: 100%; max-width: 256px; display: block; margin: auto; }}
table.grid {{ width: 100%; table-layout: fixed; }}  /* many runs: tiles shrink, nothing scrolls */
table.grid th.label {{ width: 9em; }}
body > img, figure img {{ max-width: 100%; }}
figure {{ margin: 0 0 12px; }}
h3 {{ margin-bottom: 0.2em; }}
.warning {{ background: #fff3cd; border: 1px solid #e0b000; padding: 6px 10px; }}
</style>
<script>
window.__errors = [];
window.addEventListener("error", e => window.__errors.push(String(e.message || e.type)), true);
window.addEventListener("load", () => {{
  const imgs = Array.from(document.images);
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  const s = document.getElementById("selfcheck");
  const overflow = Math.max(0, document.documentElement.scrollWidth - window.innerWidth);  // scrolls sideways
  s.textContent = `images=${{imgs.length}} broken=${{broken}} errors=${{window.__errors.length}} overflow=${{overflow}}`;
}});
</script></head><body>
<h1>Intrinsic Autoencoder evaluation</h1>
<p>Decomposition data: <code>{html.escape(str(data))}</code>; real images: <code>{html.escape(str(real))}</code>;
FID intrinsics: <code>{html.escape(str(intrinsics))}</code>.</p>
{warn_html}
<h2>Table 1: realism of R's images (FID / KID against real images, lower is better)</h2>
{table(*_table1(entries))}
<p>FID from fewer than {FID_MIN_IMAGES} images per set is biased upwards and marked so; KID is unbiased, so small
comparisons should lean on it. The paper's figures are printed for reference (its setting: 256x512, 16,000 real
photos, full training), not as a like-for-like comparison.</p>
<h2>Table 3: decomposition errors against Cycles ground truth</h2>
<p>{html.escape(TABLE3_NOTE)}</p>
{table(*_table3(entries))}
<h2>Deferred neural rendering: the same intrinsics through each run's R</h2>
<table class="grid" style="max-width: {272 * (3 + len(renderers))}px"><thead><tr>{ren_head}</tr></thead>
<tbody>{''.join(ren_rows)}</tbody></table>
<h2>Intrinsic decomposition: each run's H next to the ground truth</h2>
<table class="grid" style="max-width: {9 * 16 + 272 * 4}px"><thead><tr><th class="label"></th><th>image</th>
<th>normal</th><th>albedo</th><th>reflection</th></tr></thead>
<tbody>{''.join(dec_rows)}</tbody></table>
{reference_html}
{gallery_html}
<h2>Data sets</h2>
<p>Training intrinsics, real images and the evaluation set must not share samples (refused otherwise); FID fakes
are R's renders of intrinsics the runs never saw.</p>
{table(*_datasets_table(datasets))}
<h2>Training losses</h2>
{curves}
<p id="selfcheck" hidden>not loaded</p>
</body></html>
"""
