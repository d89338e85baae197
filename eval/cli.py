"""`iae-eval`: decomposition errors, FID/KID and the comparison report."""
from __future__ import annotations

import tempfile
from pathlib import Path

import click

from blender_gen.dataset import DatasetError


def _fail(exc: Exception) -> None:
    raise click.ClickException(str(exc)) from None


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Evaluate Intrinsic Autoencoder runs (and baselines) as numbers and pictures."""


@main.command()
@click.option("--run", "run_dir", type=click.Path(path_type=Path), default=None, help="Run folder: its H decomposes --data.")
@click.option("--predictions", type=click.Path(path_type=Path), default=None,
              help="Or a folder of predictions in the dataset format (any method).")
@click.option("--data", required=True, type=click.Path(path_type=Path), help="PBR dataset with ground truth.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Summary JSON (per-sample CSV beside it); default: decomposition.json in the predictions folder.")
@click.option("--limit", type=int, default=None, help="Only the first N samples.")
@click.option("--quiet", is_flag=True)
def decomposition(run_dir, predictions, data, out, limit, quiet) -> None:
    """Normal angles and albedo/reflection L1 of predictions against PBR ground truth."""
    from .decomposition import format_table, score_predictions, write_results

    if (run_dir is None) == (predictions is None):
        raise click.ClickException("give exactly one of --run DIR or --predictions DIR")
    try:
        if run_dir is not None:
            from train.inference import decompose_images

            # predictions are kept next to the summary (or in a fresh temporary folder)
            predictions = Path(tempfile.mkdtemp(prefix="iae_pred_")) / "predictions" if out is None \
                else out.with_name(out.stem + "_predictions")
            decompose_images(run_dir, data, predictions, limit=limit, progress=not quiet)
        rows, summary = score_predictions(data, predictions, progress=not quiet)
        summary_path, csv_path = write_results(rows, summary, out or predictions / "decomposition.json")
    except (DatasetError, ValueError, FileExistsError) as exc:
        _fail(exc)
    click.echo(format_table(summary))
    click.echo(f"summary {summary_path}\nper-sample {csv_path}")


@main.command()
@click.option("--real", required=True, type=click.Path(path_type=Path), help="Photo folder or PBR dataset.")
@click.option("--fake", type=click.Path(path_type=Path), default=None, help="Folder of generated images.")
@click.option("--run", "run_dir", type=click.Path(path_type=Path), default=None, help="Or render the fakes with this run's R ...")
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None, help="... from this intrinsics dataset.")
@click.option("--limit", type=int, default=None, help="At most N images per set.")
@click.option("--inception", type=click.Path(dir_okay=False), default=None, help="TorchScript Inception weights file.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, help="Write the result as JSON.")
@click.option("--quiet", is_flag=True)
def fid(real, fake, run_dir, intrinsics, limit, inception, out, quiet) -> None:
    """FID and KID (100 subsets of at most 1000 images; raw and x100) with TF Inception-v3 features."""
    from .fid import InceptionFeatures, InceptionWeightsError, extract, fid_from_features, kid_from_features
    from .images import image_source

    if (fake is None) == (run_dir is None):
        raise click.ClickException("give --fake DIR, or --run DIR with --intrinsics DIR")
    try:
        model = InceptionFeatures(inception)
        if run_dir is not None:
            if intrinsics is None:
                raise click.ClickException("--run needs --intrinsics DIR to render the fake images from")
            from train.inference import render_dataset

            fake = Path(tempfile.mkdtemp(prefix="iae_fake_"))
            render_dataset(run_dir, intrinsics, fake, limit=limit, progress=not quiet)
        n_r, r_it = image_source(real, limit)
        n_f, f_it = image_source(fake, limit)
        rf = extract(model, r_it, n_r, progress=not quiet, desc="real")
        ff = extract(model, f_it, n_f, progress=not quiet, desc="fake")
        kid, kid_std = kid_from_features(rf, ff)
        result = {"fid": fid_from_features(rf, ff), "kid": kid, "kid_std": kid_std, "real_images": len(rf),
                  "fake_images": len(ff), "real": str(real), "fake": str(fake)}
    except (DatasetError, InceptionWeightsError, ValueError) as exc:
        _fail(exc)
    click.echo(f"FID {result['fid']:.3f}   KID {result['kid']:.5f} ± {result['kid_std']:.5f} "
               f"(x100: {100 * result['kid']:.3f})   over {len(rf)} real / {len(ff)} fake images")
    if out:
        from blender_gen.dataset import atomic_write_json

        atomic_write_json(out, result)


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--data", required=True, type=click.Path(path_type=Path), help="PBR dataset (decomposition ground truth).")
@click.option("--real", required=True, type=click.Path(path_type=Path), help="Real images for FID/KID.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None,
              help="Intrinsics to render for FID and the grids (default: each run's training set).")
@click.option("--limit", default=50, show_default=True, type=int, help="Images per set for FID and decomposition.")
@click.option("--grid", default=4, show_default=True, type=int, help="Samples in the picture grids.")
@click.option("--inception", type=click.Path(dir_okay=False), default=None)
@click.option("--quiet", is_flag=True)
def report(runs, data, real, out, intrinsics, limit, grid, inception, quiet) -> None:
    """Tables like the paper's (1: FID/KID, 3: decomposition), image grids and loss curves: HTML + Markdown."""
    from .fid import InceptionWeightsError
    from .report import build_report

    try:
        page = build_report(list(runs), data, real, out, intrinsics, limit, grid, inception, progress=not quiet)
    except (DatasetError, InceptionWeightsError, ValueError) as exc:
        _fail(exc)
    click.echo(f"{page}\n{Path(out) / 'report.md'}")
    click.echo((Path(out) / "report.md").read_text())


if __name__ == "__main__":
    main()
