"""Automatic part labelling: inference on a synthetic car, rules proposed from it,
and the CLI on a real model when ../shared/assets is there."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from blender_gen.cars.labeller import FaceTable, agreement, face_normals, infer, infer_up, propose_rules
from blender_gen.cars.rules import load_rules, rule_labels

ROOT = Path(__file__).resolve().parent.parent
ASSETS = ROOT.parent / "shared" / "assets"

# palette: colour and the UV cell it sits in (a texture of distinct swatches, like Kenney's)
PAINT, GLASS, RED, YELLOW, DARK, RIM = ((0.2, 0.3, 0.8), (0.1, 0.1)), ((0.85, 0.93, 1.0), (0.3, 0.1)), \
    ((0.9, 0.15, 0.15), (0.5, 0.1)), ((1.0, 0.85, 0.2), (0.7, 0.1)), ((0.12, 0.12, 0.13), (0.1, 0.5)), \
    ((0.75, 0.75, 0.78), (0.3, 0.5))


def _box(lo, hi, colours) -> list[tuple[np.ndarray, tuple]]:
    """12 outward-wound triangles of an axis-aligned box; `colours(axis, sign)` picks each side's swatch."""
    lo, hi = np.array(lo, float), np.array(hi, float)
    tris = []
    for axis in range(3):
        for sign in (-1, 1):
            u, v = [k for k in range(3) if k != axis]
            if sign < 0:
                u, v = v, u  # keep the winding outward
            c = np.where(np.arange(3) == axis, hi if sign > 0 else lo, 0.0)
            corners = []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = c.copy()
                p[u] = (lo, hi)[a][u]
                p[v] = (lo, hi)[b][v]
                corners.append(p)
            sw = colours(axis, sign)
            tris += [(np.array([corners[0], corners[1], corners[2]]), sw), (np.array([corners[0], corners[2], corners[3]]), sw)]
    return tris


def synthetic_car(flip: bool = False) -> tuple[FaceTable, dict[str, np.ndarray]]:
    """A car of boxes facing +X (or -X with `flip`): blue paint, a narrower cabin whose sides are
    glass, four wheels named wheel_* (dark tread, light hub face), red lamps at the back and
    yellow ones at the front; the body's floor is painted like the body but is its underside.
    Returns the table and the true part of every face."""
    faces: list[tuple[np.ndarray, tuple, str, str]] = []
    add = lambda tris, obj, part_of: faces.extend((t, sw, obj, part_of(sw)) for t, sw in tris)  # noqa: E731
    add(_box((-2, -0.9, 0.3), (2, 0.9, 1.0), lambda a, s: PAINT), "body", lambda sw: "body")
    add(_box((-1, -0.7, 1.0), (1, 0.7, 1.5), lambda a, s: PAINT if a == 2 else GLASS), "body",
        lambda sw: "body" if sw == PAINT else "windows")
    for x in (-1.3, 1.3):
        for y in (-0.8, 0.8):
            add(_box((x - 0.3, y - 0.12, 0.0), (x + 0.3, y + 0.12, 0.6), lambda a, s, y=y: RIM if a == 1 and s * y > 0 else DARK),
                f"wheel_{x}_{y}", lambda sw: "rims" if sw == RIM else "tyres")
    for y in (-0.6, 0.6):
        add(_box((-2.05, y - 0.15, 0.7), (-2.0, y + 0.15, 0.85), lambda a, s: RED), "body", lambda sw: "tail_lights")
        add(_box((2.0, y - 0.15, 0.7), (2.05, y + 0.15, 0.85), lambda a, s: YELLOW), "body", lambda sw: "headlights")
    tris = np.array([f[0] for f in faces])
    if flip:
        tris = tris * np.array([-1.0, -1.0, 1.0])  # turned 180 degrees about the vertical
    n = len(tris)
    fn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    table = FaceTable(tris=tris, normals=np.repeat(fn[:, None], 3, axis=1),
                      objects=np.array([f[2] for f in faces], dtype=object), materials=np.full(n, "palette", dtype=object),
                      uv=np.array([f[1][1] for f in faces], float) + 0.01, colour=np.array([f[1][0] for f in faces], float),
                      textured=np.ones(n, bool), alpha=np.ones(n), transmission=np.zeros(n), emission=np.zeros(n))
    parts = np.array([f[3] for f in faces], dtype=object)
    parts[(table.objects == "body") & (fn[:, 2] < -0.9) & (tris[:, :, 2].mean(1) < 0.5)] = "underbody"
    return table, {"parts": parts}


@pytest.mark.parametrize("flip", [False, True])
def test_infer_finds_orientation_glass_wheels_and_lamps(flip):
    table, truth = synthetic_car(flip)
    lab = infer(table)
    assert (lab.up, lab.forward) == ("+Z", "-X" if flip else "+X")
    areas = table.areas()
    for part in ("windows", "tyres", "rims", "tail_lights", "headlights", "body", "underbody"):
        sel = truth["parts"] == part
        assert sel.any(), part
        assert agreement(lab.labels[sel], truth["parts"][sel], areas[sel]) > 0.95, part
    assert set(lab.evidence[truth["parts"] == "tyres"]) == {"name"}
    assert not lab.warnings


def test_up_is_where_the_car_narrows_without_wheel_names():
    table, _ = synthetic_car()
    # rotate so that the car's up is -Y (an OBJ authored Z-up, read as Y-up)
    rot = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # new y = -z, new z = y
    assert infer_up(table.tris @ rot.T, table.areas()) == "-Y"
    assert infer_up(table.tris, table.areas()) == "+Z"


def test_transparent_materials_are_glass_unless_they_are_the_whole_body():
    table, truth = synthetic_car()
    glass = truth["parts"] == "windows"
    table.materials = np.where(glass, "clear", "paint").astype(object)
    table.colour[:] = 0.5  # no colour cue left: only the material says it
    table.alpha = np.where(glass, 0.3, 1.0)
    lab = infer(table, forward="+X", up="+Z")
    assert (lab.labels[glass] == "windows").all() and set(lab.evidence[glass]) == {"material"}
    # an OBJ importer's "transmission 1" on the body material itself is no glass
    table.alpha[:] = 1.0
    table.materials[:] = "body"
    table.transmission = np.ones(len(table))
    lab = infer(table, forward="+X", up="+Z")
    assert not (lab.labels == "windows").any()
    assert any("no windows" in w for w in lab.warnings)


def test_proposed_rules_load_and_reproduce_the_inference(tmp_path):
    table, _ = synthetic_car()
    lab = infer(table)
    text = propose_rules(table, lab, "synthetic.glb", length=4.2)
    path = tmp_path / "r.toml"
    path.write_text(text)
    rules = load_rules(path)
    assert (rules.model.forward, rules.model.up, rules.model.length) == ("+X", "+Z", 4.2)
    assert tomllib.loads(text)["rule"]
    again, hits = rule_labels(table, rules, "body")
    assert agreement(again, lab.labels, table.areas()) > 0.99


@pytest.mark.skipif(not (ASSETS / "cars3d" / "sedan.glb").is_file(), reason="needs ../shared/assets")
def test_label_parts_cli_on_a_kenney_model_and_auto_rules_render(tmp_path):
    model = ASSETS / "cars3d" / "sedan.glb"
    cli = [sys.executable, "-c", "from blender_gen.cli import main; main()"]
    run = subprocess.run(cli + ["label-parts", str(model), "--out", str(tmp_path / "sedan.toml"),
                                "--preview", str(tmp_path / "sedan.png")], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert "forward -Y, up +Z" in run.stdout and "tyres" in run.stdout and "windows" in run.stdout
    # the proposal is re-applied as the importer would and reproduces the inference
    reproduced = re.search(r"give the inferred part to ([0-9.]+)% of the area", run.stdout)
    assert reproduced and float(reproduced.group(1)) > 85, run.stdout
    assert (tmp_path / "sedan.png").stat().st_size > 10000
    rules = load_rules(tmp_path / "sedan.toml")
    assert rules.model.forward == "-Y"
    # a stylised model (2.55 units long): its category from the roof, the sedans' typical length
    assert "category sedan, length 4.72 m" in run.stdout
    assert (rules.model.category, rules.model.length) == ("sedan", 4.72)
    # existing files are not overwritten without --force
    again = subprocess.run(cli + ["label-parts", str(model), "--out", str(tmp_path / "sedan.toml")],
                           capture_output=True, text=True, cwd=ROOT)
    assert again.returncode != 0 and "--force" in again.stderr
    # outputs that would overwrite each other are refused before any work
    same = subprocess.run(cli + ["label-parts", str(model), "--out", str(tmp_path / "x.toml"), "--preview",
                                 str(tmp_path / "x.toml")], capture_output=True, text=True, cwd=ROOT)
    assert same.returncode != 0 and "the same file as --out" in same.stderr and not (tmp_path / "x.toml").exists()
    (tmp_path / "other").mkdir()
    shutil.copy(model, tmp_path / "other" / "sedan.glb")
    twins = subprocess.run(cli + ["label-parts", str(model), str(tmp_path / "other" / "sedan.glb"), "--out",
                                  str(tmp_path / "rules")], capture_output=True, text=True, cwd=ROOT)
    assert twins.returncode != 0 and "both would write" in twins.stderr and not (tmp_path / "rules").exists()
    # --car-rules auto: the same inference inside a dataset
    gen = subprocess.run(cli + ["intrinsics", "--out", str(tmp_path / "ds"), "--count", "1", "--resolution", "64x32",
                                "--cars", str(model), "--car-rules", "auto", "--quiet"], capture_output=True, text=True,
                         cwd=ROOT)
    assert gen.returncode == 0, gen.stderr
    assert (tmp_path / "ds" / "samples" / "000000.exr").is_file()


def _body_with_arches(axles=(1.3, -1.4), radius=0.35, half_width=0.9):
    """Side walls (y = +-half_width) of a 4.4 m body from z = 0.2 to 1.3, with semicircular arches of
    radius + 0.05 over wheels standing at `axles` (x), plus a roof: small triangles, facing +X."""
    tris = []
    step = 0.05
    for x in np.arange(-2.2, 2.2, step):
        for z in np.arange(0.2, 1.3, step):
            cx, cz = x + step / 2, z + step / 2
            if any(np.hypot(cx - a, cz - radius) < radius + 0.05 for a in axles):
                continue  # the arch
            for y in (-half_width, half_width):
                tris.append([[x, y, z], [x + step, y, z], [x, y, z + step]])
    for x in np.arange(-2.2, 2.2, 0.2):
        for y in np.arange(-half_width, half_width, 0.2):
            tris.append([[x, y, 1.3], [x + 0.2, y, 1.3], [x, y + 0.2, 1.3]])
    return np.array(tris, float)


def _wheel_at_origin(radius=0.35, width=0.22, hub=0.03, n=16):
    """A tyre band around the y axis plus a hub disc protruding `hub` on the -y (right) side."""
    a = np.linspace(0, 2 * np.pi, n + 1)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], -1)
    tris = []
    for (x0, z0), (x1, z1) in zip(ring[:-1], ring[1:]):
        tris.append([[x0, -width / 2, z0], [x1, -width / 2, z1], [x0, width / 2, z0]])
        tris.append([[0, -width / 2 - hub, 0], [x0 * 0.6, -width / 2, z0 * 0.6], [x1 * 0.6, -width / 2, z1 * 0.6]])
    return np.array(tris, float)


def _table(parts: list[tuple[np.ndarray, str]]):
    tris = np.concatenate([t for t, _ in parts])
    n = len(tris)
    normals = np.repeat(face_normals(tris)[:, None], 3, axis=1)
    objects = np.concatenate([[name] * len(t) for t, name in parts]).astype(object)
    return FaceTable(tris=tris, normals=normals, objects=objects, materials=np.full(n, "", object),
                     uv=np.full((n, 2), np.nan), colour=np.full((n, 3), np.nan), textured=np.zeros(n, bool),
                     alpha=np.ones(n), transmission=np.zeros(n), emission=np.zeros(n))


def test_wheel_files_modelled_at_the_origin_go_into_the_arches_and_are_mirrored():
    """A body plus wheel files authored at the origin (MetaDrive's Beetle) loads as one
    car: each wheel in the arch its name says, mirrored to the other side, all on one axle height."""
    from blender_gen.cars.rules import RulesError
    from blender_gen.cars.wheels import find_arches, place_wheel_files

    body, wheel = _body_with_arches(), _wheel_at_origin()
    front, back = find_arches(body.mean(1), 0.35)
    assert front.x == pytest.approx(1.3, abs=0.1) and back.x == pytest.approx(-1.4, abs=0.1)
    assert front.top == pytest.approx(0.75, abs=0.06) and front.outer == pytest.approx(0.9, abs=1e-6)
    names = ["body.gltf", "right_tire_front.gltf", "right_tire_back.gltf"]
    table = _table([(body, "body"), (wheel, "tire"), (wheel, "tire")])
    index = np.repeat([0, 1, 2], [len(body), len(wheel), len(wheel)])
    placed, report = place_wheel_files(table, index, names, "+X", "+Z")
    assert len(report) == 4 and sum("mirrored" in line for line in report) == 2
    wheels = placed.tris[placed.objects == "tire"]
    assert len(wheels) == 4 * len(wheel) and (placed.objects == "body").sum() == len(body)
    centres = sorted(tuple(np.round((w.reshape(-1, 3).min(0) + w.reshape(-1, 3).max(0)) / 2, 2))
                     for w in np.split(wheels, 4))
    xs, ys, zs = np.array(centres).T
    assert sorted(set(np.round(xs, 1))) == [-1.4, 1.3]  # the two axles
    assert (np.abs(ys) > 0.6).all() and (np.abs(ys) < 0.9).all() and sorted(np.sign(ys)) == [-1, -1, 1, 1]
    assert np.ptp(zs) < 1e-6 and zs[0] == pytest.approx(0.35, abs=0.06)  # level, standing about on z = 0
    outer = np.abs(wheels.reshape(-1, 3)[:, 1]).max()
    assert 0.85 < outer < 0.9  # just inside the body's side
    # the mirrored copies keep their faces wound outwards: hubs point away from the car on both sides
    for w in np.split(wheels, 4):
        hub = w[np.abs(w[:, :, 1]).max(1) == np.abs(w.reshape(-1, 3)[:, 1]).max()]
        assert len(hub) and (np.sign(face_normals(hub)[:, 1]) == np.sign(w.reshape(-1, 3)[:, 1].mean())).all()
    # a file that names the other side is not mirrored over ("rear" is the back axle too)
    three = _table([(body, "body"), (wheel, "tire"), (wheel, "tire"), (-wheel, "tire")])
    names3 = ["body.gltf", "right_tire_front.gltf", "right_tire_rear.gltf", "left_tire_rear.gltf"]
    _, report = place_wheel_files(three, np.repeat([0, 1, 2, 3], [len(body)] + [len(wheel)] * 3), names3, "+X", "+Z")
    assert len(report) == 4 and [line for line in report if "mirrored" in line] == [report[1]], report
    # placed wheels are left alone; a body without arches is a clear error
    again, report = place_wheel_files(placed, np.repeat([0, 1], [len(body), 4 * len(wheel)]), names[:2], "+X", "+Z")
    assert report == [] and np.array_equal(again.tris, placed.tris)
    flat = _table([(_body_with_arches(axles=()), "body"), (wheel, "tire")])
    with pytest.raises(RulesError, match="no front and back wheel arch"):
        place_wheel_files(flat, np.repeat([0, 1], [len(flat) - len(wheel), len(wheel)]), names[:2], "+X", "+Z")


def test_rules_limited_to_files_and_heights(tmp_path):
    # two grey faces of one palette swatch, one low (a sill), one high (a roof)
    tris = np.array([[[0, 0, 0.0], [1, 0, 0.0], [0, 1, 0.1]], [[0, 0, 0.9], [1, 0, 0.9], [0, 1, 1.0]]])
    table = FaceTable(tris=tris, normals=np.repeat(face_normals(tris)[:, None], 3, axis=1),
                      objects=np.array(["body", "body"], object), materials=np.array(["m", "m"], object),
                      uv=np.array([[0.45, 0.3], [0.45, 0.3]]), colour=np.full((2, 3), 0.3), textured=np.ones(2, bool),
                      alpha=np.ones(2), transmission=np.zeros(2), emission=np.zeros(2))
    path = tmp_path / "r.toml"
    path.write_text('[[rule]]\nmatch = "palette"\nfiles = ["police*.glb"]\nheight = [0.5, 1.0]\nuv_min = [0.4, 0.25]\n'
                    'uv_max = [0.5, 0.5]\npart = "body"\n'
                    '[[rule]]\nmatch = "palette"\nuv_min = [0.4, 0.25]\nuv_max = [0.5, 0.5]\npart = "bumpers"\n')
    rules = load_rules(path)
    assert list(rule_labels(table, rules, "body", "police.glb")[0]) == ["bumpers", "body"]
    assert list(rule_labels(table, rules, "body", "sedan.glb")[0]) == ["bumpers", "bumpers"]
    # height along the model's own up axis: upside down (-Z up), the first face is the high one
    assert list(rule_labels(table, rules, "body", "police.glb", up="-Z")[0]) == ["body", "bumpers"]
    path.write_text('[[rule]]\nmatch = "object"\npattern = "x"\nheight = [0.6, 0.2]\npart = "body"\n')
    with pytest.raises(Exception, match=r"rule #1: height must be \[low, high\]"):
        load_rules(path)


def test_rules_limited_by_facing(tmp_path):
    # a floor face (low, looking down), a roof face (high, up) and a door face (sideways), one swatch
    tris = np.array([[[0, 0, 0.1], [0, 1, 0.1], [1, 0, 0.1]], [[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]],
                     [[0, 0, 0.2], [1, 0, 0.2], [1, 0, 0.8]]])
    table = FaceTable(tris=tris, normals=np.repeat(face_normals(tris)[:, None], 3, axis=1),
                      objects=np.array(["body"] * 3, object), materials=np.array(["m"] * 3, object),
                      uv=np.full((3, 2), 0.3), colour=np.full((3, 3), 0.3), textured=np.ones(3, bool),
                      alpha=np.ones(3), transmission=np.zeros(3), emission=np.zeros(3))
    path = tmp_path / "r.toml"
    path.write_text('[[rule]]\nmatch = "object"\npattern = "*"\nheight = [0.0, 0.35]\nfacing = "down"\npart = "underbody"\n'
                    '[[rule]]\nmatch = "object"\npattern = "*"\nfacing = "side"\npart = "bumpers"\n')
    rules = load_rules(path)
    assert list(rule_labels(table, rules, "body")[0]) == ["underbody", "body", "bumpers"]
    # facing and height are along the model's own up axis: upside down, the roof is the low face looking down
    assert list(rule_labels(table, rules, "body", up="-Z")[0]) == ["body", "underbody", "bumpers"]
    path.write_text('[[rule]]\nmatch = "object"\npattern = "*"\nfacing = "below"\npart = "body"\n')
    with pytest.raises(Exception, match=r"rule #1: facing must be one of \['up', 'down', 'side'\], got 'below'"):
        load_rules(path)


@pytest.mark.skipif(not (ASSETS / "cars3d_cc_by" / "metadrive" / "beetle" / "vehicle.gltf").is_file(),
                    reason="needs ../shared/assets")
def test_one_ctrl_c_stops_label_parts_with_130_before_its_next_file(tmp_path):
    import signal
    import time

    from blender_gen.cars.rules import load_rules

    # three models; Ctrl-C as soon as the first one's rules are written, whatever the machine's speed
    gazebo = ASSETS / "cars3d_cc_by" / "gazebo"
    models = [ASSETS / "cars3d_cc_by" / "metadrive" / "beetle" / "vehicle.gltf",
              gazebo / "hatchback" / "meshes" / "hatchback.obj", gazebo / "suv" / "meshes" / "suv.obj"]
    out = tmp_path / "rules"
    proc = subprocess.Popen([sys.executable, "-c", "from blender_gen.cli import main; main()", "label-parts",
                             *map(str, models), "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    first = out / "vehicle.toml"
    deadline = time.monotonic() + 120
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, "label-parts ended before its first rules file was written"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert load_rules(first)  # the file written before the Ctrl-C is whole
    assert not (out / "suv.toml").exists()  # the model not yet started writes nothing
    assert sorted(p.name for p in out.iterdir()) in (["vehicle.png", "vehicle.toml"], ["vehicle.toml"],
                                                     ["hatchback.toml", "vehicle.png", "vehicle.toml"])


@pytest.mark.skipif(not (ASSETS / "cars3d_cc_by" / "metadrive" / "beetle" / "vehicle.gltf").is_file(),
                    reason="needs ../shared/assets")
def test_a_car_in_several_files_takes_the_body_first_and_each_file_once(tmp_path):
    beetle = ASSETS / "cars3d_cc_by" / "metadrive" / "beetle"
    cli = [sys.executable, "-c", "from blender_gen.cli import main; main()", "label-parts"]
    for token, message in ((f"{beetle / 'right_tire_front.gltf'}+{beetle / 'vehicle.gltf'}", "the body comes first"),
                           (f"{beetle / 'vehicle.gltf'}+{beetle / 'vehicle.gltf'}", "a file named twice")):
        proc = subprocess.run(cli + [token, "--out", str(tmp_path / "r.toml")], capture_output=True, text=True,
                              cwd=ROOT)
        assert proc.returncode == 1 and message in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert not (tmp_path / "r.toml").exists()


def test_category_and_length_guesses_on_the_named_catalogue():
    """The labeller's category cues on the 28 named models (built without bpy, true categories known):
    every sedan, wagon and van right, 24 of 28 in all; lengths in metres are kept."""
    import numpy as np

    from blender_gen.cars.body import build_car
    from blender_gen.cars.catalogue import load_catalogue
    from blender_gen.cars.labeller import guess_category, guess_length

    right, by_cat = 0, {}
    for name, spec in load_catalogue().items():
        tris = []
        for m in build_car(spec).values():
            for k in range(1, m.faces.shape[1] - 1):
                tris.append(m.verts[np.stack([m.faces[:, 0], m.faces[:, k], m.faces[:, k + 1]], 1)])
        t = np.concatenate(tris)
        lo, hi = t.reshape(-1, 3).min(0), t.reshape(-1, 3).max(0)
        size = hi - lo
        c = (t.mean(1) - (lo + hi) / 2) / (size / 2)
        c[:, 2] = (t.mean(1)[:, 2] - lo[2]) / size[2]
        guess = guess_category(c, size)
        right += guess == spec.category
        by_cat.setdefault(spec.category, []).append(guess == spec.category)
        assert guess_length(guess, float(size[0])) == round(float(size[0]), 2)  # metres: kept
    assert right >= 24
    assert all(by_cat["sedan"]) and all(by_cat["station_wagon"]) and all(by_cat["van"])
    assert guess_length("van", 2.75) == 5.05  # toy units: the category's typical length


def test_a_ctrl_c_inside_the_gltf_importer_is_an_interrupt_not_a_bad_file(tmp_path, monkeypatch):
    """Blender's glTF operator catches a KeyboardInterrupt raised in its Python and reports it as a
    RuntimeError; reading a model turns that back into the interrupt (exit 130, "interrupted"), so a
    Ctrl-C while a slow model imports is not "cannot be imported"."""
    from types import SimpleNamespace

    from blender_gen.cars import faces

    def interrupted(filepath):
        raise RuntimeError("Error: Python: Traceback (most recent call last):\n  ...\nKeyboardInterrupt\n")

    def broken(filepath):
        raise RuntimeError("Error: Python: Traceback (most recent call last):\n  ...\nValueError: bad accessor\n")

    for importer, expected in ((interrupted, KeyboardInterrupt), (broken, RuntimeError)):
        fake = SimpleNamespace(data=SimpleNamespace(objects=[]),
                               context=SimpleNamespace(preferences=SimpleNamespace(filepaths=SimpleNamespace())),
                               ops=SimpleNamespace(import_scene=SimpleNamespace(gltf=importer)))
        monkeypatch.setattr(faces, "bpy", fake)
        with pytest.raises(expected):
            faces.read_objects(tmp_path / "car.gltf")
