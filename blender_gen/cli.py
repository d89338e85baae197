"""`iae-gen`: the dataset generator's command line."""
from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import click

from .camera import CameraRanges, Orbit
from .cli_errors import one_line_errors
from .dataset import MAX_INDEX
from .envmap import PROCEDURAL_SETS
from .generate import generate, merge
from .recipe import Recipe
from .cars.rules import MODEL_SUFFIXES, split_car

EXR_MAGIC = b"\x76\x2f\x31\x01"


def _fail(msg: str) -> None:
    raise click.ClickException(msg)


def _finite_option(ctx, param, value):
    """click's FloatRange lets NaN through (every comparison with it is false)."""
    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"{value!r}: expected a finite number")
    return value


def parse_resolution(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not m:
        _fail(f"--resolution {text!r}: expected WIDTHxHEIGHT, e.g. 512x256")
    w, h = int(m.group(1)), int(m.group(2))
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        _fail(f"--resolution {text!r}: width and height must be between 8 and 8192 pixels")
    return w, h


def check_envmap(path: str) -> str:
    """Early, Blender-free check that an environment map is a readable .hdr/.exr file."""
    if path in PROCEDURAL_SETS:
        return "procedural" if path == "procedural:train" else path  # one spelling, one recipe identity
    p = Path(path)
    if not p.is_file():
        _fail(f"--envmap {path}: no such file")
    suffix = p.suffix.lower()
    if suffix not in (".hdr", ".exr"):
        _fail(f"--envmap {path}: expected an equirectangular .hdr or .exr file")
    with open(p, "rb") as fh:
        head = fh.read(16)
    if suffix == ".hdr" and not head.startswith(b"#?"):
        _fail(f"--envmap {path}: not a Radiance HDR file (no '#?' header)")
    if suffix == ".exr" and not head.startswith(EXR_MAGIC):
        _fail(f"--envmap {path}: not an OpenEXR file (bad magic number)")
    return str(p.resolve())


def _expand_cars(chunk: str, option: str = "--cars") -> list[str]:
    """One --cars argument as car tokens: a folder gives every model file under it, a glob pattern
    its matches, and a name that is an existing file is taken whole (even with ',' or '+' in it);
    otherwise comma-separated tokens (catalogue names, FILE or BODY+WHEELS files)."""
    import glob

    chunk = chunk.strip()
    path = Path(chunk)
    if path.is_dir():
        files = sorted(str(f) for f in path.rglob("*") if f.is_file() and f.suffix.lower() in MODEL_SUFFIXES)
        if not files:
            _fail(f"{option} {chunk}: a folder without model files ({', '.join(MODEL_SUFFIXES)})")
        return files
    if path.is_file():
        return [chunk]
    if any(c in chunk for c in "*?["):
        files = sorted(f for f in glob.glob(chunk, recursive=True) if Path(f).suffix.lower() in MODEL_SUFFIXES)
        if not files:
            _fail(f"{option} {chunk}: the pattern matches no model file ({', '.join(MODEL_SUFFIXES)})")
        return files
    return [t.strip() for t in chunk.split(",")]


def check_cars(tokens: tuple[str, ...], rules: str | None, option: str = "--cars") -> tuple[str, ...]:
    """The car tokens of `option`'s arguments, each checked: model files exist and have rules,
    catalogue names select cars; a bad one exits with a one-line error naming `option`."""
    from .cars import load_catalogue, select_cars

    out, names = [], []
    for token in (t for chunk in tokens for t in _expand_cars(chunk, option)):
        if not token:
            continue
        if Path(token).suffix.lower() in MODEL_SUFFIXES or "/" in token:
            # one car in several files: BODY+WHEELS (a file whose own name holds '+' is taken whole)
            files = split_car(token)
            if len({p.resolve() for p in files}) < len(files):
                _fail(f"{option} {token}: a file named twice in one car (its faces would be doubled)")
            for p in files:
                if not p.is_file():
                    _fail(f"{option} {token}: no such model file {p}")
                if p.suffix.lower() not in MODEL_SUFFIXES:
                    _fail(f"{option} {token}: unsupported model format {p.suffix!r}; expected one of {MODEL_SUFFIXES}")
            if rules is None:
                _fail(f"{option} {token}: a model file needs --car-rules FILE (or --car-rules auto) to map its "
                      "objects to parts")
            out.append("+".join(str(p.resolve()) for p in files))
        else:
            names.append(token)
            out.append(token)
    if names:
        try:
            select_cars(load_catalogue(), ",".join(names))
        except ValueError as exc:  # the selectors' messages speak of --cars
            msg = str(exc)
            _fail(option + msg.removeprefix("--cars") if msg.startswith("--cars") else msg)
    if not out:
        _fail(f"{option}: no car given")
    return tuple(out)


def _rules_arg(rules: str | None) -> str | None:
    return None if rules is None else "auto" if rules == "auto" else str(Path(rules).resolve())


class WorkersType(click.ParamType):
    """A number of Blender processes (1-256), or auto."""

    name = "N|auto"

    def convert(self, value, param, ctx):
        text = str(value).strip().lower()
        if text == "auto":
            return "auto"
        if text.isdigit() and 1 <= int(text) <= 256:
            return int(text)
        self.fail(f"{value!r}: expected a number of processes from 1 to 256, or auto", param, ctx)


WORKERS_HELP = ("Blender processes rendering in parallel, each pinned to its share of the CPUs; auto: one per "
                "usable CPU, at most 8, and at least 8 samples each. The files are the same bytes either way.")


def _common_options(fn):
    opts = [
        click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
                     help="Dataset folder (created; re-running resumes it)."),
        click.option("--count", required=True, type=click.IntRange(1, MAX_INDEX + 1),
                     help="Number of samples in the dataset."),
        click.option("--seed", default=0, show_default=True, type=click.IntRange(0), help="Recipe seed: same seed, same dataset."),
        click.option("--resolution", default="512x256", show_default=True, help="WIDTHxHEIGHT in pixels."),
        click.option("--cars", "cars", multiple=True,
                     help="Catalogue selectors (procedural, procedural:train, procedural:heldout, a category, "
                          "model names; comma-separated or repeated), procedural:random[:CATEGORY][@SEED] (a new "
                          "seeded car for every block of views, never like a held-out model) or model files "
                          "with --car-rules. Each block of --views-per-car views draws one entry: a model file "
                          "given N times gets N shares of the views."),
        click.option("--car-rules", type=click.Path(dir_okay=False), default=None,
                     help="TOML rules mapping a model file's objects/materials/palette regions to parts, or "
                          "'auto' (parts inferred per model: see `iae-gen label-parts`)."),
        click.option("--envmap", "envmaps", multiple=True,
                     help="Equirectangular .hdr/.exr (repeatable), or the built-in skies: procedural (= "
                          "procedural:train, 8 skies) or procedural:heldout (4 others). Default: intrinsics "
                          "procedural, pbr procedural:heldout (the stand-in for real photos)."),
        click.option("--samples", default=None, type=click.IntRange(1, 1 << 16), help="Cycles samples per pixel."),
        click.option("--workers", default="auto", show_default=True, type=WorkersType(), help=WORKERS_HELP),
        click.option("--shard", default=None, help="I/N: render only samples with index % N == I (batch schedulers)."),
        click.option("--radius-min", default=CameraRanges.radius_min, show_default=True, type=float,
                     help="Minimum horizontal camera distance from the car centre (m)."),
        click.option("--radius-max", default=CameraRanges.radius_max, show_default=True, type=float,
                     help="Maximum horizontal camera distance (m); the paper uses 8."),
        click.option("--height-min", default=CameraRanges.height_min, show_default=True, type=float),
        click.option("--height-max", default=CameraRanges.height_max, show_default=True, type=float,
                     help="Maximum camera height (m); the paper uses 3."),
        click.option("--focal-range", default=f"{CameraRanges.focal_min:g}-{CameraRanges.focal_max:g}",
                     show_default=True, help="Focal length range in mm (36 mm sensor)."),
        click.option("--min-coverage", default=CameraRanges.min_coverage, show_default=True, type=float,
                     help="Minimum fraction of the frame the car's bounding box must cover."),
        click.option("--max-coverage", default=CameraRanges.max_coverage, show_default=True, type=float,
                     help="Maximum fraction. Below 1 the framing is drawn instead of the distance: a coverage "
                          "uniform between the two (as far as each view allows), the camera distance solved "
                          "for it; photo-like framing is about 0.3-0.7 (see `iae-eval framing`)."),
        click.option("--views-per-car", default=4, show_default=True, type=click.IntRange(1, MAX_INDEX + 1),
                     help="Consecutive samples that share a (randomly drawn) car model; 1 = a new draw per sample."),
        click.option("--quiet", is_flag=True, help="No progress bar."),
    ]
    for opt in reversed(opts):
        fn = opt(fn)
    return fn


def _build_recipe(kind: str, default_cars: str, default_samples: int, o: dict,
                  default_env: str = "procedural") -> Recipe:
    samples = default_samples if o["samples"] is None else o["samples"]
    w, h = parse_resolution(o["resolution"])
    m = re.fullmatch(r"\s*([\d.]+)\s*-\s*([\d.]+)\s*", o["focal_range"])
    if not m:
        _fail(f"--focal-range {o['focal_range']!r}: expected MIN-MAX in mm, e.g. 24-60")
    ranges = CameraRanges(radius_min=o["radius_min"], radius_max=o["radius_max"], height_min=o["height_min"],
                          height_max=o["height_max"], focal_min=float(m.group(1)), focal_max=float(m.group(2)),
                          min_coverage=o["min_coverage"], max_coverage=o["max_coverage"])
    try:
        ranges.validate()
    except ValueError as exc:
        _fail(str(exc))
    rules = o["car_rules"]
    if rules is not None and rules != "auto" and not Path(rules).is_file():
        _fail(f"--car-rules {rules}: no such file (or 'auto')")
    cars = check_cars(o["cars"] or (default_cars,), rules)
    if rules is not None:
        from .cars.rules import RulesError, load_rules

        try:
            load_rules(rules)
        except RulesError as exc:
            _fail(str(exc))
    envmaps = tuple(check_envmap(e) for e in o["envmaps"]) or (default_env,)
    return Recipe(kind=kind, seed=o["seed"], width=w, height=h, cars=cars,
                  car_rules=_rules_arg(rules), envmaps=envmaps, samples=samples,
                  camera=ranges, views_per_car=o["views_per_car"], background=o.get("background", "black"))


def _run(recipe: Recipe, o: dict) -> None:
    from .generate import Interrupted

    try:
        with one_line_errors():
            info = generate(recipe, o["out"], o["count"], workers=o["workers"], shard=o["shard"],
                            progress=not o["quiet"])
    except Interrupted as exc:
        click.echo(f"{o['out']}: stopped; every finished sample is kept: run the same command again to resume",
                   err=True)
        sys.exit(128 + exc.signum)
    n, secs = info["_rendered"], info["_seconds"]
    rate = f", {n / secs:.2f} samples/s" if n and secs > 0 else ""
    click.echo(f"{o['out']}: {info['count']} samples ({n} rendered now in {secs:.1f} s{rate})")
    if not info["complete"]:
        _fail(f"{o['out']}: INCOMPLETE ({info['count']} samples finished); run the same command "
              "again to finish it")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="intrinsic-autoencoders")
def main() -> None:
    """Synthetic data for the Intrinsic Autoencoder: intrinsics and Cycles PBR datasets."""


@main.command()
@_common_options
@click.option("--background", type=click.Choice(["environment", "black"]), default="environment", show_default=True,
              help="environment: the reflection layer shows the environment behind the car, so a real image's "
                   "sky and ground are expressible as intrinsics (docs/experiment_log.md: Making it learn); black: all layers 0 there.")
def intrinsics(**o) -> None:
    """Render the synthetic intrinsic maps M_s (normal, albedo, reflection, mask)."""
    _run(_build_recipe("intrinsics", "procedural:train", 1, o), o)


@main.command()
@_common_options
@click.option("--noise-threshold", default=Recipe.noise_threshold, show_default=True, type=click.FloatRange(0, 1, max_open=True),
              help="Cycles' adaptive sampling: a pixel stops once the image is this clean, so its light layers can "
                   "stay noisier; 0 = every pixel takes all --samples (converged light layers).")
def pbr(**o) -> None:
    """Render Cycles path-traced images with their ground-truth intrinsics.

    The defaults make the stand-in for real photos: held-out cars under held-out skies. The
    Table-3 evaluation set is `--cars procedural:train --envmap procedural` with a new --seed.
    """
    if not math.isfinite(o["noise_threshold"]):
        _fail(f"--noise-threshold {o['noise_threshold']}: expected a number in [0, 1)")
    recipe = _build_recipe("pbr", "procedural:heldout", 8, o, default_env="procedural:heldout")
    _run(replace(recipe, noise_threshold=o["noise_threshold"]), o)


@main.command()
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Dataset folder; frame k is sample k (re-running resumes it).")
@click.option("--car", "car", required=True, help="One catalogue car (see `iae-gen cars`) or a model file with --car-rules.")
@click.option("--car-rules", type=click.Path(dir_okay=False), default=None)
@click.option("--frames", required=True, type=click.IntRange(1, MAX_INDEX + 1), help="Frames in one full orbit.")
@click.option("--radius", default=Orbit.radius, show_default=True, type=click.FloatRange(min=0, min_open=True), callback=_finite_option,
              help="Camera distance from the car's centre (m).")
@click.option("--height", "cam_height", default=Orbit.height, show_default=True, type=float, help="Camera height (m).")
@click.option("--focal", default=None, type=click.FloatRange(min=0, min_open=True), callback=_finite_option,
              help="Focal length (mm, 36 mm sensor); default: the longest that shows the whole car in every frame.")
@click.option("--start", default=0.0, show_default=True, type=float, help="Angle of the first frame (degrees).")
@click.option("--envmap", default=None, help="Equirectangular .hdr/.exr or a built-in sky set (default: procedural).")
@click.option("--env-rotation", default=None, type=float, help="Environment rotation (degrees; default: drawn from --seed).")
@click.option("--paint", default=None, help="Body paint by name (default: drawn from --seed).")
@click.option("--pbr", is_flag=True, help="Render the Cycles image too (a `pbr` dataset): Cycles' video of the same path.")
@click.option("--background", type=click.Choice(["environment", "black"]), default="environment", show_default=True,
              help="Intrinsics only: the reflection layer's background, as in `iae-gen intrinsics` (R trained on "
                   "environment backgrounds expects them); a --pbr path's layers are the ground truth, black there.")
@click.option("--samples", default=None, type=click.IntRange(1, 1 << 16), help="Cycles samples per pixel (--pbr: 8).")
@click.option("--resolution", default="512x256", show_default=True, help="WIDTHxHEIGHT in pixels.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0))
@click.option("--workers", default="auto", show_default=True, type=WorkersType(), help=WORKERS_HELP)
@click.option("--quiet", is_flag=True)
def turntable(out, car, car_rules, frames, radius, cam_height, focal, start, envmap, env_rotation, paint, pbr, background,
              samples, resolution, seed, workers, quiet) -> None:
    """Intrinsics (or, with --pbr, Cycles images and intrinsics) of a camera orbiting one car.

    `iae-train render --run RUN --intrinsics OUT --out DIR --video R.mp4` turns them into R's video;
    `iae-eval flicker` compares its frame-to-frame change with Cycles' on the same path.
    """
    from .materials import load_materials

    for name, value in (("--radius", radius), ("--height", cam_height), ("--focal", focal), ("--start", start),
                        ("--env-rotation", env_rotation)):
        if value is not None and not math.isfinite(value):  # click's ranges let NaN through
            _fail(f"{name} {value}: expected a finite number")
    paints = load_materials().paints
    if paint is not None and paint not in paints:
        _fail(f"--paint {paint!r}: no such paint; expected one of {', '.join(paints)}")
    if "," in car:
        _fail(f"--car {car!r}: a turntable shows one car")
    cars = check_cars((car,), car_rules, "--car")
    if not Path(cars[0]).suffix:
        from .cars import load_catalogue, select_cars

        chosen = select_cars(load_catalogue(), cars[0])
        if len(chosen) != 1:
            _fail(f"--car {car!r}: selects {len(chosen)} cars; name one (see `iae-gen cars`)")
    orbit = Orbit(frames=frames, radius=radius, height=cam_height, focal=focal, start_deg=start, paint=paint,
                  env_rotation_deg=env_rotation)
    o = {"out": out, "count": frames, "seed": seed, "resolution": resolution, "cars": (car,), "car_rules": car_rules,
         "envmaps": (envmap,) if envmap else (), "samples": samples, "workers": workers, "shard": None,
         "radius_min": CameraRanges.radius_min, "radius_max": CameraRanges.radius_max,
         "height_min": CameraRanges.height_min, "height_max": CameraRanges.height_max,
         "focal_range": f"{CameraRanges.focal_min:g}-{CameraRanges.focal_max:g}",
         "min_coverage": CameraRanges.min_coverage, "max_coverage": CameraRanges.max_coverage, "views_per_car": 1, "quiet": quiet,
         "background": "black" if pbr else background}
    recipe = _build_recipe("pbr" if pbr else "intrinsics", car, 8 if pbr else 1, o)
    _run(replace(recipe, orbit=orbit), o)


@main.command("cars")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--cars", "cars", multiple=True, help="Selectors or model files (default: the whole catalogue).")
@click.option("--car-rules", type=click.Path(dir_okay=False), default=None)
@click.option("--columns", default=4, show_default=True, type=click.IntRange(1, 64))
@click.option("--count", default=24, show_default=True, type=click.IntRange(1, 1000),
              help="Cars drawn from a procedural:random selector.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(0), help="Seed of procedural:random cars.")
@click.option("--quiet", is_flag=True)
def cars_cmd(out: Path, cars: tuple[str, ...], car_rules: str | None, columns: int, count: int, seed: int,
             quiet: bool) -> None:
    """A contact sheet (one PNG) of car models in a fixed view, to judge them at a glance.

    `--cars procedural:random --count 24 --seed 5` shows the first 24 random cars of seed 5:
    the cars a dataset with `--cars procedural:random --seed 5` draws, in its order.
    """
    from .contact_sheet import contact_sheet

    if car_rules is not None and car_rules != "auto" and not Path(car_rules).is_file():
        _fail(f"--car-rules {car_rules}: no such file (or 'auto')")
    chosen = check_cars(cars or ("procedural",), car_rules)
    with one_line_errors():
        path = contact_sheet(out, chosen, _rules_arg(car_rules), columns=columns,
                             count=count, seed=seed, progress=not quiet)
    click.echo(str(path))


@main.command("label-parts")
@click.argument("models", nargs=-1, required=True)
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="RULES.toml for one model; a folder (NAME.toml each) for several.")
@click.option("--preview", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Part-colour PNG (side, front, top, bottom) for one model; with several, NAME.png in --out.")
@click.option("--length", default=None, type=click.FloatRange(0.5, 30), callback=_finite_option,
              help="Bumper-to-bumper length in metres written to the rules (default: the model's own length "
                   "where its units look like metres for the category guessed, else that category's typical length).")
@click.option("--forward", type=click.Choice(["+X", "-X", "+Y", "-Y", "+Z", "-Z"]), default=None,
              help="The model's front axis after import (default: inferred from its lamps or profile).")
@click.option("--up", type=click.Choice(["+X", "-X", "+Y", "-Y", "+Z", "-Z"]), default=None,
              help="The model's up axis after import (default: inferred: the axis roof and hood face).")
@click.option("--force", is_flag=True, help="Overwrite existing rules/preview files.")
def label_parts(models: tuple[str, ...], out: Path, preview: Path | None, length: float | None, forward: str | None,
                up: str | None, force: bool) -> None:
    """Propose a rules file for car models that have none (glass, wheels, lights, ... inferred).

    MODEL is a .glb/.gltf/.obj/.blend file, or several joined by '+' (a body and its wheels). Prints
    per part its faces, area and the evidence that decided it, and what could not be found; the
    proposed rules are re-applied and their agreement with the inference printed.
    `--car-rules auto` on the other commands uses the same inference on the fly.
    """
    tokens = check_cars(models, "auto")
    several = len(tokens) > 1
    if several and out.suffix:
        _fail(f"--out {out}: several models need a folder for their rules files (NAME.toml each)")
    if several and preview is not None:
        _fail("--preview: one PNG for one model; with several, NAME.png is written beside each NAME.toml")
    if (forward is None) != (up is None):
        _fail("--forward and --up: give both or neither")
    if forward is not None and forward[1] == up[1]:
        _fail(f"--forward {forward} --up {up}: the two axes must differ (front and roof cannot face one way)")
    if preview is not None and preview.resolve() == out.resolve():
        _fail(f"--preview {preview}: the same file as --out; the picture would replace the rules")
    names: dict[str, str] = {}
    for token in tokens:
        name = split_car(token)[0].stem
        if several and name in names:
            _fail(f"{names[name]} and {token}: both would write {out / (name + '.toml')}; "
                  "label models with one file name into separate --out folders")
        names[name] = token
    targets = []
    for token in tokens:
        name = split_car(token)[0].stem
        rules_path = out / f"{name}.toml" if several else out
        png = out / f"{name}.png" if several else preview
        for path in (rules_path, png):
            if path is not None and path.exists() and not force:
                _fail(f"{path}: exists; pass --force to overwrite")
        targets.append((token, name, rules_path, png))
    import importlib
    import signal

    importlib.import_module("bpy")  # importing bpy takes over SIGINT below Python (Ctrl-C was ignored)

    # One Ctrl-C stops the command. The flag holds it too when the KeyboardInterrupt lands in a garbage
    # collector's callback, where Python swallows it; the loop checks the flag before each file it writes.
    stop = {"asked": False}

    def on_ctrl_c(signum: int, frame: object) -> None:
        stop["asked"] = True
        raise KeyboardInterrupt

    def unraisable(info: "sys.UnraisableHookArgs") -> None:  # the swallowed Ctrl-C is in the flag: no traceback
        if not isinstance(info.exc_value, KeyboardInterrupt):
            sys.__unraisablehook__(info)

    sys.unraisablehook = unraisable
    signal.signal(signal.SIGINT, on_ctrl_c)
    try:
        _label_targets(targets, forward, up, length, lambda: stop["asked"])
        if stop["asked"]:
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        click.echo("interrupted: the rules files not yet written are not written", err=True)
        sys.exit(130)


def _label_targets(targets: list, forward: str | None, up: str | None, length: float | None,
                   stop_asked: Callable[[], bool] = lambda: False) -> None:
    from .cars.faces import read_car
    from .cars.importer import model_files
    from .cars.labeller import infer, preview as draw_preview, propose_rules, rules_reproduce
    from .cars.rules import RulesError
    from .dataset import atomic_target

    for token, name, rules_path, png in targets:
        with one_line_errors():
            table, placed = read_car(model_files(token), forward, up)
            try:
                lab = infer(table, forward=forward, up=up)
            except RulesError as exc:
                raise RulesError(f"{token}: {exc}") from None
        for line in placed:
            click.echo(f"{name}: placed {line}")
        areas = table.areas()
        text = propose_rules(table, lab, split_car(token)[0].name, length=length)
        if stop_asked():
            raise KeyboardInterrupt
        rules_path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_target(rules_path) as tmp:
            Path(tmp).write_text(text, encoding="utf-8")
        try:
            reproduced = rules_reproduce(table, lab, rules_path, str(split_car(token)[0]))
        except RulesError as exc:
            _fail(f"{rules_path}: the proposed rules do not load ({exc}); please report this model")
        click.echo(f"{name}: {len(table)} faces, forward {lab.forward}, up {lab.up}, category {lab.category}, length {length if length is not None else lab.length:g} m -> {rules_path}")
        for part, faces, share, why in lab.summary(areas):
            ev = ", ".join(f"{k} {v}" for k, v in sorted(why.items(), key=lambda kv: -kv[1]))
            click.echo(f"  {part:16s} {faces:6d} faces {100 * share:5.1f}% of area   ({ev})")
        for w in lab.warnings:
            click.echo(f"  warning: {w}")
        click.echo(f"  the proposed rules give the inferred part to {100 * reproduced:.1f}% "
                   "of the area")
        if png is not None:
            if stop_asked():
                raise KeyboardInterrupt
            png.parent.mkdir(parents=True, exist_ok=True)
            with atomic_target(png) as tmp:
                draw_preview(table, lab.labels, lab.forward, lab.up, tmp, title=f"{name}: inferred parts")
            click.echo(f"  preview: {png}")


@main.command("inspect")
@click.argument("root", type=click.Path(path_type=Path))
@click.option("--grid", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Preview grid PNG (default: ROOT/previews/inspect_grid.png).")
@click.option("--grid-samples", default=6, show_default=True, type=click.IntRange(1, 64))
@click.option("--max-stats", default=None, type=click.IntRange(0), help="Gather value ranges over the first N samples only.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--quiet", is_flag=True)
def inspect_cmd(root: Path, grid: Path | None, grid_samples: int, max_stats: int | None, as_json: bool,
                quiet: bool) -> None:
    """Summarise a dataset, verify every checksum, write a preview grid; exit 1 if anything is wrong."""
    from .inspect import format_summary, inspect_dataset, preview_grid

    with one_line_errors():
        summary = inspect_dataset(root, max_stats=max_stats, progress=not quiet)
        if summary["samples"] > len(summary["bad_files"]):
            summary["grid"] = str(preview_grid(root, grid or Path(root) / "previews" / "inspect_grid.png",
                                               grid_samples, frozenset(summary["bad_files"])))
    click.echo(json.dumps(summary, indent=2) if as_json else format_summary(summary))
    if summary.get("grid") and not as_json:
        click.echo(f"preview   {summary['grid']}")
    if not summary["complete"]:
        sys.exit(1)


@main.command("status")
@click.argument("folders", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON (every missing index listed).")
def status_cmd(folders: tuple[Path, ...], as_json: bool) -> None:
    """The shards of one sharded run: missing and damaged samples, shards not started, whether it can be merged;
    exit 1 until it can. Rerunning an unfinished shard's command repairs exactly what is listed."""
    from .status import format_status, run_status

    with one_line_errors():
        st = run_status(list(folders))
    click.echo(json.dumps(st, indent=2) if as_json else format_status(st))
    if not st["ready_to_merge"]:
        sys.exit(1)


@main.command("convert")
@click.argument("root", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--to", "fmt", required=True, type=click.Choice(["npy", "png16"]),
              help="npy: float32 arrays in the dataset's units; png16: 16-bit PNGs (encodings in conversion.json).")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="A new or empty folder.")
@click.option("--layers", default=None, help="Comma-separated layers (default: all of the set's).")
@click.option("--quiet", is_flag=True)
def convert_cmd(root: Path, fmt: str, out: Path, layers: str | None, quiet: bool) -> None:
    """A dataset as one file per sample and layer (OUT/LAYER/NNNNNN.npy|png) for tools without EXR."""
    from .convert import convert_dataset

    with one_line_errors():
        path = convert_dataset(root, out, fmt, [x.strip() for x in layers.split(",")] if layers else None,
                               progress=not quiet)
    click.echo(f"{path}: {fmt} files, encodings in {path / 'conversion.json'}")


@main.command("merge")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.argument("shards", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--quiet", is_flag=True)
def merge_cmd(out: Path, shards: tuple[Path, ...], quiet: bool) -> None:
    """Join shard folders (from --shard I/N runs of one recipe) into one dataset."""
    with one_line_errors():
        info = merge(out, list(shards), progress=not quiet)
    msg = f"{out}: {info['count']} samples merged from {len(shards)} shard(s)"
    click.echo(msg)
    if info["_missing"]:
        _fail(f"{out}: INCOMPLETE, {len(info['_missing'])} sample(s) missing, e.g. {info['_missing'][:10]}")


if __name__ == "__main__":
    main()
