"""`iae-train`: train the Intrinsic Autoencoder (or a baseline), render and decompose."""
from __future__ import annotations

import math
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
@click.version_option(package_name="intrinsic-autoencoders")
def main() -> None:
    """Intrinsic Autoencoder training and inference."""


def _note_unread_photos(folder, option: str) -> None:
    """Say on stderr which photos of a folder are left out for their format (HEIC, raw, ...)."""
    from .data import unread_photos_note

    if folder is not None and (note := unread_photos_note(Path(folder), option)):
        click.echo(note, err=True)


@main.command()
@click.option("--config", "config", default=None, help="Preset (paper, cpu-small, cyclegan, munit) or a TOML file.")
@click.option("--intrinsics", type=click.Path(), default=None, help="Intrinsics dataset (M_s).")
@click.option("--real", type=click.Path(), default=None,
              help="PBR dataset or folder of photos: JPG, PNG, WebP, BMP or TIFF (I_r).")
@click.option("--run-dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Run folder; an existing one is resumed where it stopped.")
@click.option("--objective", type=click.Choice(["default", "paper"]), default=None,
              help="With --config: put this objective on the preset's networks and sizes: the measured defaults "
                   "(the deferred shader R) or the paper's (its pix2pixHD R and Eq. 7). Default: the preset's own.")
@click.option("--set", "overrides", multiple=True, help="Override a config value: section.key=value (repeatable).")
@click.option("--max-steps", type=click.IntRange(1), default=None,
              help="Stop after this many steps (default: optim.max_steps).")
@click.option("--probe", type=click.Path(), default=None,
              help="PBR set with ground truth, never used for gradients: every run.probe_every steps H's errors, the "
                   "constant predictor's and R's input sensitivity go to stats.jsonl, TensorBoard and probe.png.")
@click.option("--device", default="auto", show_default=True, help="cpu, cuda, cuda:N or auto.")
@click.option("--accept-changed-data", is_flag=True,
              help="Resume although --intrinsics or --real changed since the run last trained (recorded in the run).")
@click.option("--init-from", type=click.Path(file_okay=False), default=None,
              help="A new run starts from this run's newest weights (fine-tuning, e.g. on your own data); "
                   "its config is the default.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def fit(config, intrinsics, real, run_dir, objective, overrides, max_steps, probe, device, accept_changed_data,
        init_from, quiet) -> None:
    """Train a model; under `torchrun --nproc_per_node K` it trains on K processes.

    Ctrl-C or SIGTERM saves a checkpoint after the current step; the same command resumes.
    """
    from .config import load_config
    from .loop import Interrupted, NonFiniteLoss, fit as run_fit

    if overrides and not (config or init_from):
        raise click.UsageError("--set needs --config or --init-from (a resumed run keeps its saved config)")
    if objective and not config:
        raise click.UsageError("--objective needs --config (the preset whose networks it goes on)")
    _note_unread_photos(real, "--real")
    try:
        with one_line_errors(EXPECTED + (NonFiniteLoss,)):
            if config:
                from .config import objective_overrides

                extra = objective_overrides(config, objective) if objective else []
                cfg = load_config(config, [*extra, *overrides])
            elif init_from and overrides:  # the source run's config, changed where --set says
                from .config import apply_overrides
                from .inference import load_run_options

                cfg = apply_overrides(load_run_options(Path(init_from))[1], list(overrides))
            else:
                cfg = None
            result = run_fit(run_dir, cfg, intrinsics, real, max_steps, _device(device), progress=not quiet,
                             probe=probe, accept_changed_data=accept_changed_data, init_from=init_from)
    except Interrupted as exc:
        click.echo(f"{run_dir}: {exc}", err=True)
        sys.exit(128 + exc.signum)
    rate = result["steps_run"] / result["seconds"] if result["seconds"] > 0 else 0.0
    click.echo(f"{run_dir}: step {result['step']} ({result['steps_run']} steps in {result['seconds']:.1f} s, "
               f"{rate:.2f} it/s)")


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--probe", required=True, type=click.Path(path_type=Path),
              help="PBR set with ground truth: I_r and the supervised direction come from it.")
@click.option("--checkpoint", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A checkpoint of the run (default: its newest), e.g. RUN/checkpoints/step_00001000.safetensors.")
@click.option("--batch", type=click.IntRange(2, 256), default=8, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Which intrinsics and probe images form the batch.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the figures as JSON.")
@click.option("--force", is_flag=True, help="Replace an existing --json file (never one inside a run or dataset folder).")
@click.option("--device", default="auto", show_default=True)
def diagnose(run_dir, probe, checkpoint, batch, seed, json_out, force, device) -> None:
    """Per loss term: its gradient norm on H_N, H_A, H_F and R and its cosine with the supervised direction."""
    from .diagnose import diagnose_run, format_diagnosis

    with one_line_errors(EXPECTED + (ValueError,)):
        if json_out:
            from blender_gen.outputs import refuse_output

            refuse_output(json_out, "--json", force)
        result = diagnose_run(run_dir, probe, checkpoint, batch, seed, _device(device))
        if json_out:
            from blender_gen.dataset import atomic_write_json

            atomic_write_json(json_out, result)
    click.echo(format_diagnosis(result))


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--intrinsics", required=True, type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="A new or empty folder for the PNGs.")
@click.option("--style-seed", default=0, show_default=True, type=int, help="Seed of random style codes (MUNIT).")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N samples (default: all).")
@click.option("--device", default="auto", show_default=True)
@click.option("--video", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the frames, in sample order, as a video (.mp4 or .gif): e.g. of `iae-gen turntable`.")
@click.option("--side-by-side", is_flag=True,
              help="Video frames show normal, albedo, reflection, R's image and (PBR data) Cycles' image.")
@click.option("--fps", default=12.0, show_default=True, type=click.FloatRange(min=1, max=120))
@click.option("--force", is_flag=True, help="Replace an existing --video file (never one inside a run folder).")
@click.option("--quiet", is_flag=True)
def render(run_dir, intrinsics, out, style_seed, limit, device, video, side_by_side, fps, force, quiet) -> None:
    """Apply R to an intrinsics dataset: one sRGB PNG per sample (and optionally a video)."""
    from .inference import render_dataset

    if side_by_side and video is None:
        raise click.UsageError("--side-by-side needs --video FILE")
    if not math.isfinite(fps):  # click's range lets NaN through
        raise click.BadParameter(f"{fps}: expected frames per second between 1 and 120", param_hint="--fps")
    with one_line_errors():
        paths = render_dataset(run_dir, intrinsics, out, _device(device), style_seed=style_seed, limit=limit,
                               progress=not quiet, video=video, side_by_side=side_by_side, fps=fps,
                               force_video=force)
    click.echo(f"{out}: {len(paths)} images" + (f"; video {video}" if video else ""))


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--images", required=True, type=click.Path(path_type=Path), help="PBR dataset or folder of photos.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="A new or empty folder for the predictions dataset.")
@click.option("--limit", type=click.IntRange(1), default=None, help="Only the first N images (default: all).")
@click.option("--size", default=None, metavar="photo|N|WxH",
              help="Photos' maps: at each photo's own size (photo, the default; at most 2048 a side), with the "
                   "longer side N (aspect kept), or exactly WIDTHxHEIGHT.")
@click.option("--strict", is_flag=True, help="Exit with status 1 when a photo could not be read (default: skip it, "
                                             "name it and say how many).")
@click.option("--device", default="auto", show_default=True)
@click.option("--quiet", is_flag=True)
def decompose(run_dir, images, out, limit, size, strict, device, quiet) -> None:
    """Apply H to photos or a PBR dataset: normal, albedo and reflection.

    Photos: H sees each whole photo (aspect kept, no crop, no padding: resized to about the pixel
    count it trained at); OUT/photos/ holds NAME_normal/_albedo/_reflection/_render.png and
    NAME.exr (the maps in linear light, float) at the photo's size (--size), and a labelled panel
    NAME.png per photo (index.html shows them all). An unreadable photo is skipped and named; the
    others are written. Always: an EXR predictions dataset at the training size (the PBR set's
    resolution for a PBR set, which `iae-eval decomposition` scores)."""
    from .inference import PhotosSkipped, decompose_images
    from .photos import parse_size
    from .run_folder import RunFolder

    with one_line_errors():
        RunFolder(run_dir).options()  # a mistyped --run fails before the photos are scanned
        _note_unread_photos(images, "--images")
        try:
            path = decompose_images(run_dir, images, out, _device(device), limit=limit, progress=not quiet,
                                    size=parse_size(size))
        except PhotosSkipped as exc:
            if strict:
                raise
            click.echo(f"warning: {exc}", err=True)
            path = exc.out
    gallery = path / "photos" / "index.html"
    click.echo(f"{path}: predictions written" + (f"; open {gallery}" if gallery.exists() else ""))


@main.command()
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
@click.option("--net", required=True, type=click.Choice(["R", "H"]), help="R: intrinsics -> image; H: image -> intrinsics.")
@click.option("--format", "fmt", default="onnx", show_default=True, type=click.Choice(["onnx", "torchscript"]))
@click.option("--out", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--resolution", default=None, help="WIDTHxHEIGHT of the exported network (default: the training size).")
@click.option("--half", is_flag=True, help="float16 weights and tensors (for GPU runtimes).")
@click.option("--no-check", is_flag=True, help="Skip comparing the file's output with PyTorch's.")
@click.option("--force", is_flag=True, help="Replace an existing --out file (never one inside a run folder).")
def export(run_dir, net, fmt, out, resolution, half, no_check, force) -> None:
    """Write R or H of a run's newest checkpoint as ONNX or TorchScript, with its tensor conventions
    (channels, encodings, ranges, run and checkpoint) in the file's metadata; batch size is dynamic."""
    from .export import export_network, parse_resolution

    with one_line_errors():
        res = parse_resolution(resolution) if resolution else None
        done = export_network(run_dir, net, fmt, out, res, half, force=force)
        click.echo(f"{out}: {net} of {run_dir} (step {done.metadata['step']}), {fmt}, "
                   f"{done.metadata['width']}x{done.metadata['height']}, {done.metadata['dtype']}")
        if not no_check and not (half and fmt == "torchscript"):  # CPU PyTorch lacks some float16 kernels
            _report_check(out, run_dir)


@main.command("check-export")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--run", "run_dir", required=True, type=click.Path(path_type=Path))
def check_export_cmd(file, run_dir) -> None:
    """Check that FILE was exported from RUN's newest checkpoint and reproduces its output."""
    with one_line_errors():
        _report_check(file, run_dir)


def _report_check(file: Path, run_dir: Path) -> None:
    from .export import check_export

    r = check_export(file, run_dir)
    click.echo(f"{file}: max |difference| to PyTorch {r['max_abs_diff']:.2e} (mean {r['mean_abs_diff']:.2e}, "
               f"tolerance {r['tolerance']:.0e}): {'ok' if r['ok'] else 'MISMATCH'}")
    if not r["ok"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
