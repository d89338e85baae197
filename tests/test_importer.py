"""Importing real models with part rules: the CC0 Kenney kit, OBJ, .blend safety, errors."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from blender_gen.cars.rules import RulesError, load_rules

from .conftest import ROOT, SHARED_ASSETS, assets_mark, run_gen

pytestmark = pytest.mark.blender
KENNEY = SHARED_ASSETS / "cars3d"
RULES = ROOT / "data_manifests" / "kenney_car_kit_rules.toml"
needs_assets = assets_mark("cars3d")


def _in_blender(code: str) -> dict:
    """Run code in a fresh Python with bpy; it prints one JSON line."""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@needs_assets
def test_every_kenney_model_imports_with_its_parts_and_glass_material():
    out = _in_blender(f"""
import json, numpy as np, bpy
from blender_gen.recipe import Recipe
from blender_gen.render import SampleRenderer
from blender_gen.materials import load_materials
files = sorted(str(p) for p in __import__('pathlib').Path({str(KENNEY)!r}).glob('*.glb'))
r = SampleRenderer(Recipe(kind='intrinsics', seed=0, width=64, height=32, cars=tuple(files), car_rules={str(RULES)!r}), 1)
glass = load_materials().parts['glass'].id
res = {{}}
for spec in r.car_specs:
    car = r.car(spec)
    pts = car.points
    res[spec.name] = {{'parts': sorted(car.objects), 'category': spec.category,
        'glass': [car.objects[p]['iae_material'] == glass for p in ('windshield', 'window_side', 'window_rear') if p in car.objects],
        'extent': (pts.max(0) - pts.min(0)).tolist(), 'zmin': float(pts[:, 2].min())}}
print(json.dumps(res))
""")
    assert set(out) == {"ambulance", "delivery", "firetruck", "police", "race", "sedan", "van"}
    for name, r in out.items():
        assert {"body", "tyres", "rims"} <= set(r["parts"]), name
        assert r["glass"] and all(r["glass"]), f"{name}: glass parts get the glass material"
        assert abs(r["zmin"]) < 1e-6, f"{name}: normalised to the ground"
    lengths = load_rules(RULES)
    assert out["sedan"]["extent"][0] == pytest.approx(lengths.settings_for("sedan.glb").length, rel=1e-3)
    assert out["van"]["category"] == "van" and out["sedan"]["category"] == "sedan"
    for name in ("sedan", "police", "van", "delivery", "ambulance"):
        assert "headlights" in out[name]["parts"] and "windshield" in out[name]["parts"], name


@needs_assets
def test_a_dataset_from_the_kenney_models_passes_inspect(tmp_path):
    out = tmp_path / "kenney"
    files = ",".join(str(p) for p in sorted(KENNEY.glob("*.glb")))
    run_gen("intrinsics", "--out", str(out), "--count", "7", "--resolution", "64x32", "--cars", files,
            "--car-rules", str(RULES), "--views-per-car", "1", "--quiet")
    s = json.loads(run_gen("inspect", str(out), "--json", "--quiet").stdout)
    assert s["complete"] and not s["problems"] and s["samples"] == 7
    rows = [json.loads(x) for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert all(r["car"]["source"].startswith("import:") for r in rows)
    info = json.loads((out / "dataset.json").read_text())
    assert info["recipe"]["car_rules"]["name"] == RULES.name and len(info["recipe"]["car_rules"]["sha256"]) == 64


@needs_assets
def test_a_model_file_given_several_times_gets_that_many_shares_of_the_views(tmp_path):
    # the documented way to weight one's own car against the catalogue: five of six entries
    out = tmp_path / "weighted"
    run_gen("intrinsics", "--out", str(out), "--count", "24", "--resolution", "32x16", "--cars", "sedan_a",
            *[a for _ in range(5) for a in ("--cars", str(KENNEY / "sedan.glb"))], "--car-rules", str(RULES),
            "--views-per-car", "1", "--seed", "3", "--quiet")
    cars = [json.loads(x)["car"]["name"] for x in (out / "manifest.jsonl").read_text().splitlines()]
    assert set(cars) == {"sedan", "sedan_a"} and cars.count("sedan") >= 18, cars  # deduplicated: about 12


def test_obj_with_material_rules(tmp_path):
    (tmp_path / "car.mtl").write_text("newmtl paint\nKd 0.8 0.1 0.1\nnewmtl glass\nKd 0.1 0.1 0.2\n")
    v = []
    faces = []

    def box(x0, x1, y0, y1, z0, z1, mtl):
        base = len(v) + 1
        v.extend([(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)])
        q = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        faces.append(f"usemtl {mtl}")
        faces.extend("f " + " ".join(str(base + i) for i in f) for f in q)

    box(-2, 2, -0.9, 0.9, 0.2, 1.0, "paint")
    box(-0.5, 1.0, -0.8, 0.8, 1.0, 1.4, "glass")
    (tmp_path / "car.obj").write_text("mtllib car.mtl\no car_body\n" + "\n".join(f"v {x} {y} {z}" for x, y, z in v)
                                       + "\n" + "\n".join(faces) + "\n")
    (tmp_path / "rules.toml").write_text(
        '[model]\nforward = "+X"\nup = "+Z"\nlength = 4.0\n'
        '[[rule]]\nmatch = "material"\npattern = "glass*"\npart = "windows"\n')
    out = _in_blender(f"""
import json, bpy
from blender_gen.cars.rules import load_rules
from blender_gen.cars.importer import import_model
m = import_model({str(tmp_path / 'car.obj')!r}, load_rules({str(tmp_path / 'rules.toml')!r}))
print(json.dumps({{'counts': m.face_counts, 'unmatched': m.unmatched}}))
""")
    counts = out["counts"]
    assert counts["body"] == 12 and out["unmatched"] == 12  # the paint box, 6 quads as 12 triangles
    assert counts.get("windshield", 0) + counts.get("window_side", 0) + counts.get("window_rear", 0) == 12


def test_textures_are_found_in_the_model_package_and_a_missing_one_is_named(tmp_path):
    # Gazebo's hatchback names a texture by a Gazebo URI (model://PKG/materials/textures/X.png) that
    # Blender's OBJ importer cannot open: it printed "Failed to open dir" lines a user cannot act on.
    # The project finds the file in the package; a texture found nowhere is named once, in words.
    from PIL import Image

    pkg = tmp_path / "hatch"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "materials" / "textures").mkdir(parents=True)
    (pkg / "model.config").write_text("<model/>")
    Image.new("RGB", (4, 4), (200, 20, 20)).save(pkg / "materials" / "textures" / "paint.png")
    (pkg / "meshes" / "car.mtl").write_text("newmtl paint\nKd 1 1 1\nmap_Kd model://hatch/materials/textures/paint.png\n"
                                           "newmtl trim\nKd 0.2 0.2 0.2\nmap_Kd nowhere.png\n")
    (pkg / "meshes" / "car.obj").write_text(
        "mtllib car.mtl\no car\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\n"
        "usemtl paint\nf 1/1 2/2 3/3\nusemtl trim\nf 2/2 4/4 3/3\n")
    code = f"""
import json, bpy, numpy as np
from blender_gen.cars.faces import read_car
table, _ = read_car([__import__('pathlib').Path({str(pkg / 'meshes' / 'car.obj')!r})])
print(json.dumps({{'textured': table.textured.tolist(), 'colour': np.round(table.colour, 2).tolist()}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "Failed to open dir" not in proc.stderr + proc.stdout
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "nowhere.png" in warnings[0] and "paint.png" not in warnings[0], proc.stderr
    assert out["textured"] == [True, False]  # the paint read from the package's texture, the trim its base colour
    assert out["colour"][0][0] > 0.7 > out["colour"][0][1] and out["colour"][1][0] < 0.6



def test_a_texture_found_by_name_is_searched_within_bounds(tmp_path, monkeypatch):
    from blender_gen import recipe
    from blender_gen.recipe import texture_by_name

    lib = tmp_path / "lib"  # a model saved in a large folder: the search must not walk all of it
    model = lib / "car" / "meshes" / "car.obj"
    model.parent.mkdir(parents=True)
    model.write_text("")
    beside = lib / "car" / "materials" / "textures" / "paint[1].png"  # Gazebo's layout; a glob character
    beside.parent.mkdir(parents=True)
    beside.write_bytes(b"png")
    assert texture_by_name("paint[1].png", model) == beside
    (model.parent / "paint[1].png").write_bytes(b"png")  # one beside the model comes first
    assert texture_by_name("paint[1].png", model) == model.parent / "paint[1].png"
    deep = lib / "car" / "a" / "b" / "c" / "d" / "deep.png"  # four folders below the folder above: too deep
    deep.parent.mkdir(parents=True)
    deep.write_bytes(b"png")
    assert texture_by_name("deep.png", model) is None
    monkeypatch.setattr(recipe, "TEXTURE_SEARCH_DEPTH", 5)
    assert texture_by_name("deep.png", model) == deep
    monkeypatch.setattr(recipe, "TEXTURE_SEARCH_ENTRIES", 2)  # the entry budget stops the walk
    assert texture_by_name("deep.png", model) is None


def test_the_folder_above_is_searched_without_walking_the_model_folder_again(tmp_path, monkeypatch):
    from blender_gen import recipe
    from blender_gen.recipe import texture_by_name

    model = tmp_path / "car" / "meshes" / "car.obj"
    model.parent.mkdir(parents=True)
    model.write_text("")
    for i in range(5):  # a model folder full of files, searched once
        (model.parent / f"part{i}.obj").write_text("")
    beside = tmp_path / "car" / "materials" / "textures" / "paint.png"
    beside.parent.mkdir(parents=True)
    beside.write_bytes(b"png")
    # 'materials', 'meshes', 'textures', then the texture: found within 5 entries only if the
    # second walk does not count the model folder's six files again
    monkeypatch.setattr(recipe, "TEXTURE_SEARCH_ENTRIES", 5)
    assert texture_by_name("paint.png", model) == beside


def test_loading_a_blend_never_runs_its_scripts(tmp_path):
    marker = tmp_path / "pwned.txt"
    blend = tmp_path / "evil.blend"
    _in_blender(f"""
import json, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_cube_add(size=2)
bpy.context.object.name = "body"
t = bpy.data.texts.new("autorun.py")
t.write("open({str(marker)!r}, 'w').write('ran')\\n")
t.use_module = True  # 'Register': runs on file load when auto-execution is allowed
bpy.ops.wm.save_as_mainfile(filepath={str(blend)!r})
print(json.dumps({{'ok': True}}))
""")
    (tmp_path / "rules.toml").write_text('[model]\nforward = "+X"\n[[rule]]\nmatch = "object"\npattern = "body*"\npart = "body"\n')
    out = _in_blender(f"""
import json, bpy
bpy.context.preferences.filepaths.use_scripts_auto_execute = True  # even a permissive user setting
from blender_gen.cars.rules import load_rules
from blender_gen.cars.importer import import_model
m = import_model({str(blend)!r}, load_rules({str(tmp_path / 'rules.toml')!r}))
print(json.dumps({{'parts': sorted(m.parts)}}))
""")
    assert out["parts"] == ["body"]
    assert not marker.exists(), "the .blend's registered script must not run"


def test_rules_errors_name_the_file_and_the_rule(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[model\nforward = 1")
    with pytest.raises(RulesError, match=r"bad.toml: not valid TOML"):
        load_rules(bad)
    bad.write_text('[[rule]]\nmatch = "object"\npattern = "x"\npart = "body"\n[[rule]]\nmatch = "object"\npattern = "y"\npart = "hood"\n')
    with pytest.raises(RulesError, match=r"bad.toml rule #2: part 'hood' is not a part"):
        load_rules(bad)
    bad.write_text('[[rule]]\nmatch = "palette"\npart = "body"\n')
    with pytest.raises(RulesError, match=r"rule #1: a palette rule needs"):
        load_rules(bad)
    bad.write_text('[model]\nforward = "+Z"\nup = "+Z"\n[[rule]]\nmatch = "object"\npattern = "x"\npart = "body"\n')
    with pytest.raises(RulesError, match=r"\[model\]: forward \(\+Z\) and up \(\+Z\) must be different"):
        load_rules(bad)


@needs_assets
def test_cli_errors_for_models(tmp_path):
    nomatch = tmp_path / "nomatch.toml"
    nomatch.write_text('[[rule]]\nmatch = "object"\npattern = "no-such-object"\npart = "body"\n')
    proc = run_gen("intrinsics", "--out", str(tmp_path / "d"), "--count", "1", "--resolution", "64x32",
                   "--cars", str(KENNEY / "sedan.glb"), "--car-rules", str(nomatch), "--quiet", check=False)
    assert proc.returncode and "no rule of" in proc.stderr and "matched any face" in proc.stderr
    proc = run_gen("intrinsics", "--out", str(tmp_path / "e"), "--count", "1", "--cars", str(KENNEY / "sedan.glb"),
                   check=False)
    assert proc.returncode and "needs --car-rules" in proc.stderr
    broken = tmp_path / "broken.toml"
    broken.write_text('[[rule]]\nmatch = "shape"\npart = "body"\n')
    proc = run_gen("intrinsics", "--out", str(tmp_path / "f"), "--count", "1", "--cars", str(KENNEY / "sedan.glb"),
                   "--car-rules", str(broken), check=False)
    assert proc.returncode and "broken.toml rule #1: match must be" in proc.stderr


def test_contact_sheet_of_the_catalogue(tmp_path):
    proc = run_gen("cars", "--out", str(tmp_path), "--cars", "sedan_a,van_a,suv_e", "--columns", "2")
    from PIL import Image

    sheet = Image.open(proc.stdout.strip())
    assert sheet.size == (2 * 384, 2 * 192)
    arr = np.asarray(sheet)
    assert arr[:192, :384].std() > 10 and arr[192:, 384:].std() < 1e-6  # 3 tiles, the 4th cell blank
