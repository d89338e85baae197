"""Where cars come from: body styles, seeded random cars, held-out separation,
silhouette maths, the catalogue's distinctness, and random cars in a rendered dataset."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from blender_gen.cars import CATEGORIES, STYLES, CarSpec, RandomCars, build_car, load_catalogue, select_cars
from blender_gen.cars import sampler
from blender_gen.cars.sampler import draw_spec, random_spec, ranges_for
from blender_gen.cars.silhouette import VIEWS, diversity, iou, iou_matrix, pair_iou, silhouettes
from blender_gen.cars.spec import ARCHES, GRILLES, HEADLIGHTS, TAIL_LIGHTS, spec_problems
from blender_gen.geometry import Mesh

from .conftest import run_gen

NEEDED = ("body", "windshield", "window_side", "window_rear", "tyres", "rims", "brake_discs", "headlights",
          "indicators", "tail_lights", "grille", "bumper_front", "bumper_rear", "mirrors", "mirror_glass",
          "licence_plates", "door_handles", "underbody", "exhaust", "interior")


def _style_samples(per_style: int = 3) -> dict[str, list[CarSpec]]:
    out: dict[str, list[CarSpec]] = {}
    rng = np.random.default_rng(11)
    for cat in CATEGORIES:
        while any(len(out.get(s, [])) < per_style for s in STYLES[cat]):
            spec = draw_spec(rng, cat, "t")
            if spec is not None:
                out.setdefault(spec.body_style, []).append(spec)
    return out


def test_every_body_style_has_every_part_grounded_and_in_its_real_world_range():
    samples = _style_samples()
    assert set(samples) == {s for styles in STYLES.values() for s in styles}
    for style, specs in samples.items():
        for spec in specs:
            parts = build_car(spec)
            missing = [p for p in NEEDED if p not in parts]
            assert not missing, f"{style}: {spec} lacks {missing}"
            pts = np.concatenate([m.verts for m in parts.values()])
            assert abs(pts[:, 2].min()) < 0.01, f"{style}: tyres touch the ground"
            lo, hi = ranges_for(spec.category, spec.body_style)["length"]
            assert lo - 0.03 <= np.ptp(pts[:, 0]) <= hi + 0.03, (style, np.ptp(pts[:, 0]))
            glass = sum(len(parts[p].faces) for p in ("windshield", "window_side", "window_rear"))
            assert glass > 50, f"{style}: the greenhouse has windows"


def test_body_styles_differ_where_they_should():
    """Notchbacks have a trunk deck, vans a short hood, SUVs ground clearance."""
    s = _style_samples(4)
    deck = {k: np.mean([c.length - c.cabin_end_s for c in v]) for k, v in s.items()}
    hood = {k: np.mean([c.windshield_s for c in v]) for k, v in s.items()}
    assert deck["notchback"] > 0.6 > max(deck["hatchback"], deck["wagon"], deck["suv"], deck["van"])
    assert hood["van"] < min(hood["notchback"], hood["suv"], hood["wagon"])
    assert min(c.clearance for c in s["suv"]) > max(c.clearance for c in s["notchback"])
    assert min(deck["pickup"], min(c.length for c in s["pickup"]) - 4.9) > 0  # a long bed on a long truck


def test_a_pickups_bed_is_open_and_its_floor_clears_the_wheels():
    for spec in _style_samples(3)["pickup"]:
        body = build_car(spec)["body"]
        c, n = body.face_centroids(), body.face_normals()
        bed_x = 0.5 * spec.length - 0.5 * (spec.cabin_end_s + spec.length)  # the bed's middle
        above = (np.abs(c[:, 0] - bed_x) < 0.3) & (np.abs(c[:, 1]) < 0.3)
        top = c[above, 2].max()  # looking down into the bed: the floor is the highest surface there
        assert top < spec.tail_height - 0.3, (spec.name, top, spec.tail_height)
        assert top > 2 * spec.wheel_radius + 0.05  # above the wheel arches
        floor = above & (np.abs(c[:, 2] - top) < 1e-6)
        assert (n[floor, 2] > 0.99).all()  # facing up, into the open
        # the rails and tailgate still close the bed around: the body is as long and wide as before
        assert np.ptp(body.verts[:, 0]) > spec.length - 0.1


def test_random_cars_are_a_pure_function_of_seed_and_index():
    sampler.random_spec.cache_clear()
    a = [random_spec(5, k) for k in range(6)]
    sampler.random_spec.cache_clear()
    b = [random_spec(5, k) for k in range(6)]
    assert a == b
    assert len({c.name for c in a}) == 6 and len({(c.length, c.height) for c in a}) == 6
    assert random_spec(6, 0) != random_spec(5, 0)
    for x, y in zip(build_car(a[0]).values(), build_car(b[0]).values()):
        assert np.array_equal(x.verts, y.verts) and np.array_equal(x.faces, y.faces)
    suv = [random_spec(5, k, ("suv",)) for k in range(3)]
    assert {c.category for c in suv} == {"suv"} and suv[0].name != a[0].name


def test_random_cars_never_reproduce_a_heldout_model(monkeypatch):
    cat = load_catalogue()
    heldout = [c for c in cat.values() if c.split == "heldout"]
    assert {c.category for c in heldout} == set(CATEGORIES)
    # A draw identical to a held-out model is rejected and redrawn from the same stream.
    draws = iter([heldout[0], heldout[0], None])
    real_draw = sampler.draw_spec
    monkeypatch.setattr(sampler, "draw_spec", lambda rng, c, n, split="random": next(draws, None) or real_draw(rng, c, n))
    sampler.random_spec.cache_clear()
    spec = random_spec(123, 0, (heldout[0].category,))
    assert sampler.resembles_heldout(heldout[0])[0] == heldout[0].name
    assert spec.split == "random" and sampler.resembles_heldout(spec) is None
    monkeypatch.undo()
    sampler.random_spec.cache_clear()
    names = set(cat)
    for k in range(8):
        spec = random_spec(1, k)
        assert spec.name not in names and spec.split == "random"
        assert sampler.resembles_heldout(spec) is None


def test_named_models_are_distinct_and_the_catalogue_checks_its_specs(tmp_path):
    cat = load_catalogue()
    specs = list(cat.values())
    sils = [silhouettes(build_car(s), pixel=0.05) for s in specs]
    m = iou_matrix(sils)
    iu = np.triu_indices(len(specs), 1)
    worst = int(np.argmax(m[iu]))
    assert m[iu].max() <= 0.93, (specs[iu[0][worst]].name, specs[iu[1][worst]].name, m[iu].max())
    bad = tmp_path / "cars.toml"
    bad.write_text('[part_materials]\nbody = "paint"\n[[car]]\nname = "x"\ncategory = "sedan"\nsplit = "train"\n'
                   'length = 4.5\nwidth = 1.8\nheight = 1.45\nwheelbase = 2.7\nfront_overhang = 0.9\n'
                   'style = "wagon"\ngrille = "star"\n')
    with pytest.raises(ValueError, match=r"cars\.toml: car 'x': style 'wagon' is not one of .*grille 'star'"):
        load_catalogue(bad)


def test_spec_problems_name_the_fields():
    spec = random_spec(2, 0)
    assert spec_problems(spec) == []
    assert "headlight" in " ".join(spec_problems(CarSpec(**{**spec.__dict__, "headlight": "laser"})))
    assert "cabin_end_s" in " ".join(spec_problems(CarSpec(**{**spec.__dict__, "cabin_end_s": spec.length + 1})))
    assert "must be a positive number" in " ".join(spec_problems(CarSpec(**{**spec.__dict__, "height": float("nan")})))
    assert set(GRILLES) and set(HEADLIGHTS) and set(TAIL_LIGHTS) and set(ARCHES)


def test_random_selectors():
    cat = load_catalogue()
    (pool,) = select_cars(cat, "procedural:random")
    assert isinstance(pool, RandomCars) and pool.car(3, 1) == random_spec(3, 1)
    (vans,) = select_cars(cat, "procedural:random:van")
    assert vans.car(3, 0).category == "van"
    with pytest.raises(ValueError, match="unknown category 'boat'"):
        select_cars(cat, "procedural:random:boat")
    with pytest.raises(ValueError, match="procedural:random"):
        select_cars(cat, "procedural:nope")
    (fixed,) = select_cars(cat, "procedural:random:suv@7")
    assert fixed.car(1, 2) == fixed.car(99, 2) == random_spec(7, 2, ("suv",))
    with pytest.raises(ValueError, match="must be an integer"):
        select_cars(cat, "procedural:random@x")
    mixed = select_cars(cat, "van_a,procedural:random")
    assert mixed[0].name == "van_a" and isinstance(mixed[1], RandomCars)


def test_silhouette_iou_maths():
    box = Mesh(np.array([[-1, -0.5, 0], [1, -0.5, 0], [1, 0.5, 0], [-1, 0.5, 0],
                         [-1, -0.5, 1], [1, -0.5, 1], [1, 0.5, 1], [-1, 0.5, 1]], float),
               np.array([[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]))
    half = Mesh(box.verts * np.array([0.5, 1, 1]), box.faces)
    a, b = silhouettes(box, pixel=0.05), silhouettes(half, pixel=0.05)
    assert set(a) == set(VIEWS)
    assert a["side"].sum() == pytest.approx((2 / 0.05) * (1 / 0.05), rel=0.06)  # metric: 2 m x 1 m
    assert iou(a["side"], b["side"]) == pytest.approx(0.5, abs=0.03)
    assert iou(a["end"], b["end"]) == pytest.approx(1.0, abs=0.01)
    assert pair_iou(a, b) == pytest.approx((0.5 + 1.0 + 0.5) / 3, abs=0.03)
    m = iou_matrix([a, b, a])
    d = diversity(["a", "b", "c"], ["x", "y", "x"], m)
    assert d["within_median"] == pytest.approx(1.0) and d["closest_pair"][:2] == ["a", "c"]
    assert d["nn_category_accuracy"] == pytest.approx(2 / 3)


@pytest.mark.blender
def test_a_random_car_dataset_renders_a_new_car_per_block_and_resumes_identically(tmp_path):
    out = tmp_path / "rand"
    args = ("intrinsics", "--out", str(out), "--count", "6", "--resolution", "64x32", "--seed", "9",
            "--cars", "procedural:random", "--views-per-car", "2", "--quiet")
    run_gen(*args)
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    names = [r["car"]["name"] for r in sorted(rows, key=lambda r: r["index"])]
    assert names[0] == names[1] and names[2] == names[3] and len(set(names)) == 3
    assert names[0] == random_spec(9, 0).name and names[4] == random_spec(9, 2).name
    info = json.loads((out / "dataset.json").read_text())
    assert "catalogue" in info["recipe"], "the recipe identity names the catalogue and sampler it used"
    before = (out / "samples" / "000003.exr").read_bytes()
    (out / "samples" / "000003.exr").unlink()
    lines = (out / "manifest.jsonl").read_text().splitlines()
    (out / "manifest.jsonl").write_text("\n".join(line for line in lines if json.loads(line)["index"] != 3) + "\n")
    run_gen(*args)
    assert (out / "samples" / "000003.exr").read_bytes() == before


def test_a_recipe_is_identified_by_every_file_a_model_import_reads(tmp_path):
    """Editing an OBJ's .mtl or texture, or a glTF's external buffer, makes another recipe: a set
    extended after the edit is refused instead of mixing samples of two models."""
    from blender_gen.recipe import Recipe, companion_files, identity_diff

    (tmp_path / "tex").mkdir()
    (tmp_path / "tex" / "paint.png").write_bytes(b"png v1")
    (tmp_path / "car.mtl").write_text("newmtl body\nKd 0.8 0.1 0.1\nmap_Kd -bm 1.0 tex/paint.png\n")
    obj = tmp_path / "car.obj"
    obj.write_text("mtllib car.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl body\nf 1 2 3\n")
    assert companion_files(obj) == ["car.mtl", "tex/paint.png"]
    recipe = Recipe(kind="intrinsics", seed=0, width=64, height=32, cars=(str(obj),))
    before = recipe.identity()
    (tmp_path / "car.mtl").write_text("newmtl body\nKd 0.1 0.8 0.1\nmap_Kd -bm 1.0 tex/paint.png\n")
    assert identity_diff(before, recipe.identity()) is not None
    edited = recipe.identity()
    (tmp_path / "tex" / "paint.png").write_bytes(b"png v2")
    assert identity_diff(edited, recipe.identity()) is not None
    gltf = tmp_path / "car.gltf"
    (tmp_path / "car.bin").write_bytes(b"\0" * 12)
    gltf.write_text('{"buffers": [{"uri": "car.bin", "byteLength": 12}], '
                    '"images": [{"uri": "data:image/png;base64,AAAA"}]}')
    assert companion_files(gltf) == ["car.bin"]
    g = Recipe(kind="intrinsics", seed=0, width=64, height=32, cars=(str(gltf),))
    first = g.identity()
    (tmp_path / "car.bin").write_bytes(b"\1" * 12)
    assert identity_diff(first, g.identity()) is not None
    plain = tmp_path / "plain.obj"
    plain.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")  # a self-contained file keeps the identity it had
    assert "reads" not in Recipe(kind="intrinsics", seed=0, width=64, height=32, cars=(str(plain),)).identity()["cars"][0]


def test_cars_take_folders_globs_and_file_names_with_commas_or_plus(tmp_path):
    from blender_gen.cli import check_cars

    fleet = tmp_path / "fleet"
    (fleet / "vans").mkdir(parents=True)
    for name in ("a.glb", "vans/b.obj", "notes.txt", "c,d.glb", "e+f.glb"):
        (fleet / name).write_bytes(b"x")
    rules = "auto"
    got = check_cars((str(fleet),), rules)
    assert [Path(t).name for t in got] == ["a.glb", "c,d.glb", "e+f.glb", "b.obj"]
    assert [Path(t).name for t in check_cars((str(fleet / "*.glb"),), rules)] == ["a.glb", "c,d.glb", "e+f.glb"]
    assert check_cars((str(fleet / "c,d.glb"),), rules) == (str((fleet / "c,d.glb").resolve()),)
    from blender_gen.cars.rules import split_car

    assert split_car(fleet / "e+f.glb") == [fleet / "e+f.glb"]
    assert split_car(f"{fleet / 'a.glb'}+{fleet / 'vans' / 'b.obj'}") == [fleet / "a.glb", fleet / "vans" / "b.obj"]
    empty = tmp_path / "empty"
    empty.mkdir()
    import click

    for bad, message in ((str(empty), "a folder without model files"), (str(fleet / "*.fbx"), "matches no model file")):
        with pytest.raises(click.ClickException, match=message):
            check_cars((bad,), rules)


def test_a_gazebo_package_may_read_its_textures_and_nothing_outside_it(tmp_path):
    # Gazebo's layout: PKG/model.sdf, PKG/meshes/car.obj whose .mtl names ../materials/textures/X.png;
    # that file belongs to the model (and to the recipe's identity); without the package marker, or
    # past the package, a reference outside the model's folder is still refused
    from blender_gen.recipe import Recipe, companion_files, model_root

    pkg = tmp_path / "prius"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "materials" / "textures").mkdir(parents=True)
    (pkg / "materials" / "textures" / "paint.png").write_bytes(b"png v1")
    (pkg / "meshes" / "car.mtl").write_text("newmtl body\nmap_Kd ../materials/textures/paint.png\n")
    obj = pkg / "meshes" / "car.obj"
    obj.write_text("mtllib car.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl body\nf 1 2 3\n")
    with pytest.raises(ValueError, match="outside the model's folder"):
        companion_files(obj)
    (pkg / "model.sdf").write_text("<sdf version='1.6'/>")
    assert model_root(obj) == pkg.resolve()
    assert companion_files(obj) == ["../materials/textures/paint.png", "car.mtl"]
    recipe = Recipe(kind="intrinsics", seed=0, width=64, height=32, cars=(str(obj),))
    before = recipe.identity()
    (pkg / "materials" / "textures" / "paint.png").write_bytes(b"png v2")
    assert recipe.identity() != before
    # a texture named where it is not (a Gazebo model:// URI, a bare name) is read from the file of
    # that name in the package, so that file is hashed too; sets made before recorded it as missing
    # and keep their identity
    from blender_gen.recipe import identity_diff

    (pkg / "materials" / "textures" / "trim.png").write_bytes(b"trim v1")
    (pkg / "meshes" / "car.mtl").write_text("newmtl body\nmap_Kd ../materials/textures/paint.png\n"
                                           "newmtl trim\nmap_Kd model://prius/materials/textures/trim.png\n")
    reads = recipe.identity()["cars"][0]["reads"]
    assert {"name": "model://prius/materials/textures/trim.png", "found": "materials/textures/trim.png",
            "sha256": hashlib.sha256(b"trim v1").hexdigest()} in reads
    made_before = recipe.identity()
    made_before["cars"][0]["reads"] = [{"name": r["name"], "missing": True} if "found" in r else r for r in reads]
    assert identity_diff(made_before, recipe.identity()) is None is identity_diff(recipe.identity(), made_before)
    first = recipe.identity()
    (pkg / "materials" / "textures" / "trim.png").write_bytes(b"trim v2")
    assert identity_diff(first, recipe.identity()) is not None
    (tmp_path / "secret.png").write_bytes(b"x")
    (pkg / "meshes" / "car.mtl").write_text("newmtl body\nmap_Kd ../../secret.png\n")
    with pytest.raises(ValueError, match="outside its model package"):
        companion_files(obj)
