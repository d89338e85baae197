"""`iae-train`: train the Intrinsic Autoencoder (or a baseline), render and decompose."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from blender_gen.cli_errors import EXPECTED, one_line_errors


def _device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise click.ClickException(f"--device {name}: CUDA is not available on this machine")
    return name


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Intrinsic Autoencoder training and inference."""


@main.command()
@click.option("--config", "config", default=None, help="Preset (paper, cpu-small, cyclegan, munit) or a TOML file.")
@click.option("--intrinsics", type=click.Path(), default=None, help="Intrinsics dataset (M_s).")
@click.option("--real", type=click.Path(), default=None, help="PBR dataset or folder of JPG/PNG photos (I_r).")
@click.option("--run-dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Run folder; an existing one is resumed where it stopped.")
@click.option("--set", "overrides", multiple=True, help="Override a config value: section.key=value (repeatable).")
@click.option("--max-steps", type=click.IntRange(1), default=None,
              help="Stop after this many steps (default: optim.max_steps).")
@click.option("--device", default="auto", show_default=True, help="cpu, cuda, cuda:N or auto.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def fit(config, intrinsics, real, run_dir, overrides, max_steps, device, quiet) -> None:
    """Train a model; under `torchrun --nproc_per_node K` it trains on K processes.

    Ctrl-C or SIGTERM saves a checkpoint after the current step; the same command resumes.
    """
    from .config import load_config
    from .loop import Interrupted, NonFiniteLoss, fit as run_fit

    if overrides and not config:
        raise click.UsageError("--set needs --config (a resumed run keeps its saved config)")
    try:
        with one_line_errors(EXPECTED + (NonFiniteLoss,)):
            cfg = load_config(config, list(overrides)) if config else None
            result = run_fit(run_dir, cfg, intrinsics, real, max_steps, _device(device), progress=not quiet)
    except Interrupted as exc:
        click.echo(f"{run_dir}: {exc}", err=True)
        sys.exit(128 + exc.signum)
    rate = result["steps_run"] / result["seconds"] if result["seconds"] > 0 else 0.0
    click.echo(f"{run_dir}: step {result['step']} ({result['steps_run']} steps in {result['seconds']:.1f} s, "
               f"{rate:.2f} it/s)")


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--intrinsics", required=True, type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="A new or empty folder for the PNGs.")
@click.option("--style-seed", default=0, show_default=True, type=int, help="Seed of random style codes (MUNIT).")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N samples (default: all).")
@click.option("--device", default="auto", show_default=True)
@click.option("--quiet", is_flag=True)
def render(run_dir, intrinsics, out, style_seed, limit, device, quiet) -> None:
    """Apply R to an intrinsics dataset: one sRGB PNG per sample."""
    from .inference import render_dataset

    with one_line_errors():
        paths = render_dataset(run_dir, intrinsics, out, _device(device), style_seed=style_seed, limit=limit,
                               progress=not quiet)
    click.echo(f"{out}: {len(paths)} images")


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--images", required=True, type=click.Path(path_type=Path), help="PBR dataset or folder of photos.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="A new or empty folder for the predictions dataset.")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N images (default: all).")
@click.option("--device", default="auto", show_default=True)
@click.option("--quiet", is_flag=True)
def decompose(run_dir, images, out, limit, device, quiet) -> None:
    """Apply H to images: predicted normal/albedo/reflection as an EXR dataset plus PNG previews."""
    from .inference import decompose_images

    with one_line_errors():
        path = decompose_images(run_dir, images, out, _device(device), limit=limit, progress=not quiet)
    click.echo(f"{path}: predictions written")


if __name__ == "__main__":
    main()
