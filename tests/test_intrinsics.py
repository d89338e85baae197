"""The intrinsics renderer and generator, end to end in Blender at tiny resolutions."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from blender_gen.dataset import read_exr, read_manifest, sha256_file
from blender_gen.envmap import reflection_reference
from blender_gen.materials import BODY_MATERIAL_ID, load_materials

from .conftest import ROOT, SHARED_ASSETS, assets_mark, run_gen

pytestmark = pytest.mark.blender


def _pixel_rays(w: int, h: int, focal_px: float) -> np.ndarray:
    xs = (np.arange(w) + 0.5) - 0.5 * w
    ys = 0.5 * h - (np.arange(h) + 0.5)
    rays = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], -focal_px), axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def rendered(renderer):
    return [renderer.render_layers(i) for i in range(6)]


def test_normals_are_unit_on_the_mask_zero_off_it_and_face_the_camera(rendered):
    for layers, d in rendered:
        mask = layers["mask"][..., 0]
        n = layers["normal"]
        on = mask > 0.5
        assert on.mean() > 0.03, "the car is in the frame"
        assert np.allclose(np.linalg.norm(n[on], axis=-1), 1.0, atol=1e-3)
        assert np.all(n[~on] == 0)
        rays = _pixel_rays(n.shape[1], n.shape[0], d["pose"].focal_px(n.shape[1]))
        facing = -np.sum(n * rays, axis=-1)[on]
        assert (facing > -0.05).mean() > 0.99, "shading normals point toward the viewer (OpenGL +Z)"
        assert np.median(n[on][:, 2]) > 0.2


def test_albedo_is_the_assigned_material_and_the_body_paint(rendered):
    table = load_materials()
    by_id = {m.id: np.array(m.albedo) for m in table.parts.values()}
    for layers, d in rendered:
        ids = layers["material"][..., 0].astype(int)
        albedo = layers["albedo"]
        assert set(np.unique(ids)) <= set(range(0, BODY_MATERIAL_ID + 1))
        assert (ids == BODY_MATERIAL_ID).any(), "the body is visible"
        for mid in np.unique(ids):
            expect = np.array(d["paint"].albedo) if mid == BODY_MATERIAL_ID else by_id.get(mid, np.zeros(3))
            got = albedo[ids == mid]
            assert np.allclose(got, expect, rtol=2e-3, atol=1e-4), f"material {mid}"


def test_reflection_is_zero_without_gloss_and_matches_the_numpy_reference(renderer, rendered):
    table = load_materials()
    gloss_of = {0: 0.0, **{m.id: m.gloss for m in table.parts.values()}}
    zero_gloss = [m.id for m in table.parts.values() if m.gloss == 0.0]
    assert zero_gloss, "the table has matte materials (underbody, interior)"
    errors = []
    for layers, d in rendered:
        ids = layers["material"][..., 0].astype(int)
        gloss = np.vectorize(lambda i: d["paint"].gloss if i == BODY_MATERIAL_ID else gloss_of[i])(ids)
        refl = layers["reflection"]
        assert np.all(refl[gloss == 0] == 0)
        ref = reflection_reference(layers["normal"], d["pose"].matrix(), d["pose"].focal_px(refl.shape[1]),
                                   renderer.env_pixels(d["env"]), d["rotation"], gloss)
        on = gloss > 0
        err = np.abs(refl[on] - ref[on]).max(axis=-1)
        scale = np.maximum(np.abs(ref[on]).max(axis=-1), 0.05)
        errors.append(err / scale)
    rel = np.concatenate(errors)
    # Pixels agree up to half-float storage and the sub-pixel jitter of the one sample;
    # a few land on edges of the skyline where a tiny angle changes the texel.
    assert np.median(rel) < 0.01, np.median(rel)
    assert (rel < 0.1).mean() > 0.95, (rel < 0.1).mean()


def test_depth_part_and_gloss_layers_agree_with_the_scene(renderer, rendered):
    """depth: metres along the view axis (the car's nearest and farthest points bound it); part: the
    part whose material the material layer shows; gloss: that material's glossiness."""
    from blender_gen.camera import project
    from blender_gen.cars.spec import PARTS

    table = load_materials()
    for layers, d in rendered:
        on, off = layers["mask"][..., 0] > 0.5, layers["mask"][..., 0] <= 0
        depth, part = layers["depth"][..., 0], layers["part"][..., 0].astype(int)
        assert np.all(depth[off] == 0) and np.all(part[off] == 0) and np.all(layers["gloss"][off] == 0)
        _, z = project(d["car"].points, d["pose"], depth.shape[1], depth.shape[0])
        assert z.min() * 0.97 <= depth[on].min() <= z.min() * 1.1, (depth[on].min(), z.min())
        assert depth[on].max() <= z.max() * 1.03
        mats = d["car"].part_material
        for k in np.unique(part[on]):
            name = mats[PARTS[k - 1]]
            material = d["paint"] if name == "paint" else table.parts[name]
            want_id = BODY_MATERIAL_ID if name == "paint" else material.id
            px = (part == k) & on
            assert np.mean(layers["material"][..., 0][px] == want_id) > 0.98, PARTS[k - 1]
            assert np.allclose(layers["gloss"][..., 0][px], material.gloss, atol=2e-3), PARTS[k - 1]


def test_a_set_made_before_the_extra_layers_is_extended_without_them(tmp_path):
    """Its samples keep the layers it lists, so a resumed or extended set never mixes two formats;
    a new set lists and holds depth, part and gloss with the part names."""
    from blender_gen.dataset import open_dataset

    # in a process of its own: a renderer made here would reset the module's Blender scene
    subprocess.run([sys.executable, "-c", "import sys; from pathlib import Path; from blender_gen.generate import "
                    "generate; from blender_gen.recipe import Recipe; generate(Recipe(kind='intrinsics', seed=3, "
                    "width=64, height=32, extra_layers=()), Path(sys.argv[1]), 1, progress=False)",
                    str(tmp_path / "old")], check=True, cwd=ROOT, capture_output=True)
    run_gen("intrinsics", "--out", str(tmp_path / "old"), "--count", "2", "--resolution", "64x32", "--seed", "3",
            "--background", "black", "--quiet")
    ds = open_dataset(tmp_path / "old")
    assert ds.layers == ("normal", "albedo", "reflection", "mask", "material") and "parts" not in ds.info
    assert [sorted(read_exr(ds.root / r["file"])) for r in ds.rows] == [sorted(ds.layers)] * 2
    run_gen("intrinsics", "--out", str(tmp_path / "new"), "--count", "1", "--resolution", "64x32", "--quiet")
    new = open_dataset(tmp_path / "new")
    assert new.layers[-3:] == ("depth", "part", "gloss") and new.info["parts"][1] == "body"
    assert set(read_exr(new.root / new.rows[0]["file"])) == set(new.layers)


def test_status_lists_what_a_sharded_run_lacks_and_a_rerun_of_those_shards_repairs_it(tmp_path):
    from blender_gen.status import run_status

    common = ["--count", "5", "--resolution", "64x32", "--seed", "2", "--background", "black", "--quiet"]
    for i in (0, 1):
        run_gen("intrinsics", "--out", str(tmp_path / f"part{i}"), "--shard", f"{i}/2", *common)
    parts = [tmp_path / "part0", tmp_path / "part1"]
    assert run_status(parts)["ready_to_merge"]
    (tmp_path / "part0" / "samples" / "000002.exr").write_bytes(b"damaged")  # a sample damaged on disk
    man = tmp_path / "part1" / "manifest.jsonl"
    man.write_text("\n".join(man.read_text().splitlines()[:-1]) + "\n")  # a shard killed before its last row
    st = run_status(parts)
    assert not st["ready_to_merge"]
    assert [(s["failed"], s["missing"]) for s in st["shards"]] == [([2], []), ([], [3])]
    assert run_status(parts[:1])["absent_shards"] == [1]
    out = subprocess.run([sys.executable, "-m", "blender_gen.cli", "status", *map(str, parts)], capture_output=True,
                         text=True, cwd=ROOT)
    assert out.returncode == 1 and "rerun shard(s) 0,1 of 2" in out.stdout, out.stdout
    for i in (0, 1):  # the shards' own commands again: only what status listed is rendered
        run_gen("intrinsics", "--out", str(tmp_path / f"part{i}"), "--shard", f"{i}/2", *common)
    assert run_status(parts)["ready_to_merge"]


def test_each_part_object_carries_its_material(renderer):
    from blender_gen.cars import load_part_materials

    table = load_materials()
    mapping, tinted = load_part_materials()
    for car in renderer.cars.values():
        spec = next(s for s in renderer.car_specs if s.name == car.name)
        for part, obj in car.objects.items():
            want = mapping[part]
            if part == "window_side" and spec.tinted_rear:
                want = tinted
            if want == "paint":
                assert obj["iae_material"] == BODY_MATERIAL_ID
            else:
                assert obj["iae_material"] == table.parts[want].id, f"{car.name}.{part}"
                assert tuple(obj["iae_albedo"]) == pytest.approx(table.parts[want].albedo)


def _files(root: Path) -> dict[str, str]:
    return {p.name: sha256_file(p) for p in sorted((root / "samples").glob("*.exr"))}


def test_same_recipe_and_seed_give_identical_files(tiny_intrinsics, tmp_path):
    again = tmp_path / "again"
    run_gen("intrinsics", "--out", str(again), "--count", "4", "--resolution", "64x32", "--seed", "3", "--quiet")
    assert _files(again) == _files(tiny_intrinsics)
    assert (again / "manifest.jsonl").read_bytes() == (tiny_intrinsics / "manifest.jsonl").read_bytes()
    other = tmp_path / "other"
    run_gen("intrinsics", "--out", str(other), "--count", "2", "--resolution", "64x32", "--seed", "4", "--quiet")
    assert list(_files(other).values()) != list(_files(tiny_intrinsics).values())[:2]


def test_manifest_rows_describe_each_sample(tiny_intrinsics):
    rows = read_manifest(tiny_intrinsics / "manifest.jsonl")
    assert [r["index"] for r in rows] == [0, 1, 2, 3]
    for r in rows:
        assert r["sha256"] == sha256_file(tiny_intrinsics / r["file"])
        assert {"name", "category"} <= set(r["car"]) and r["paint"] and r["envmap"]["name"]
        assert 0 <= r["envmap"]["rotation_deg"] < 360
        cam = r["camera"]
        assert len(cam["location"]) == 3 and cam["focal_length"] > 0 and cam["resolution"] == [64, 32]
        assert np.hypot(*cam["location"][:2]) <= 8.05 and cam["location"][2] <= 3.0  # centre within cm of the origin
    info = json.loads((tiny_intrinsics / "dataset.json").read_text())
    assert info["kind"] == "intrinsics" and info["complete"] and info["count"] == 4
    assert info["resolution"] == [64, 32] and info["recipe"]["seed"] == 3


def test_resume_after_kill_finishes_with_identical_files(tmp_path):
    n = 40  # enough samples that a kill after the first finished one always lands mid-way
    recipe = ["--count", str(n), "--resolution", "64x32", "--seed", "3", "--quiet"]
    whole = tmp_path / "whole"
    run_gen("intrinsics", "--out", str(whole), *recipe)
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "blender_gen.cli", "intrinsics", "--out", str(out), *recipe],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and len(read_manifest(out / "manifest.jsonl")) < 1:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = read_manifest(out / "manifest.jsonl")
    assert 1 <= len(before) < n, "killed mid-way"
    # what a killed writer can leave: a torn manifest line and a half-written temporary file
    missing = next(i for i in range(n) if i not in {r["index"] for r in before})
    with open(out / "manifest.jsonl", "a") as fh:
        fh.write(f'{{"index": {missing}, "file": "samples/00')
    (out / "samples" / f".{missing:06d}.exr.tmp999").write_bytes(b"partial")
    (out / "previews").mkdir(exist_ok=True)
    (out / "previews" / f".{missing:06d}.png.tmp999").write_bytes(b"partial")  # a PBR worker's preview
    kept = {r["file"]: os.stat(out / r["file"]).st_mtime_ns for r in before}
    run_gen("intrinsics", "--out", str(out), *recipe)
    assert _files(out) == _files(whole)
    assert not list((out / "samples").glob(".*")) and not list((out / "previews").glob(".*"))
    for f, mtime in kept.items():
        assert os.stat(out / f).st_mtime_ns == mtime, f"{f} was finished and must not be redone"
    assert sorted(r["index"] for r in read_manifest(out / "manifest.jsonl")) == list(range(n))


def test_a_corrupted_sample_is_detected_and_redone(tiny_intrinsics, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(tiny_intrinsics, out)
    victim = out / "samples" / "000002.exr"
    victim.write_bytes(victim.read_bytes()[:100])
    bad = run_gen("inspect", str(out), "--quiet", check=False)
    assert bad.returncode == 1 and "000002.exr: checksum mismatch" in bad.stdout
    run_gen("intrinsics", "--out", str(out), "--count", "4", "--resolution", "64x32", "--seed", "3", "--quiet")
    assert _files(out) == _files(tiny_intrinsics)
    assert run_gen("inspect", str(out), "--quiet").returncode == 0


def test_rerunning_a_finished_set_writes_nothing_and_lets_a_training_start(tiny_intrinsics, tmp_path):
    """Two `reproduce` runs sharing --data: the second's check of a finished set must not look like a
    writer to the first's training. A rerun on a complete, intact set verifies it under a reader's
    lock and leaves every file as it was; a writer's lock still refuses a training."""
    import shutil

    from blender_gen.dataset import locked_folder, reading_folder
    from train.data import check_ready

    out = tmp_path / "copy"
    shutil.copytree(tiny_intrinsics, out)
    before = {p.name: (p.read_bytes(), os.stat(p).st_mtime_ns) for p in (out / "dataset.json", out / "manifest.jsonl")}
    with reading_folder(out) as held:  # another process verifying the same set meanwhile
        assert held
        check_ready(out, "--intrinsics")  # a training starts
        with pytest.raises(ValueError, match=r"--out .* is being read by another process \(checking its samples\)"):
            with locked_folder(out):  # a writer is refused, and not in the name of the set's last writer
                pass
        res = run_gen("intrinsics", "--out", str(out), "--count", "4", "--resolution", "64x32", "--seed", "3")
    assert "4 samples (0 rendered now" in res.stdout
    assert {p.name: (p.read_bytes(), os.stat(p).st_mtime_ns) for p in (out / "dataset.json", out / "manifest.jsonl")} == before
    with locked_folder(out):  # a writer: the training is refused and a reader's path steps aside
        with pytest.raises(ValueError, match="is being written by pid"):
            check_ready(out, "--intrinsics")
        with reading_folder(out) as held:
            assert not held


def test_shards_with_workers_merge_into_the_single_run(tiny_intrinsics, tmp_path):
    shards = []
    for i in range(2):
        s = tmp_path / f"shard{i}"
        run_gen("intrinsics", "--out", str(s), "--count", "4", "--resolution", "64x32", "--seed", "3",
                "--shard", f"{i}/2", "--quiet", *(["--workers", "2"] if i == 0 else []))
        assert [r["index"] % 2 for r in read_manifest(s / "manifest.jsonl")] == [i, i]
        shards.append(str(s))
    merged = tmp_path / "merged"
    run_gen("merge", "--out", str(merged), *shards, "--quiet")
    assert _files(merged) == _files(tiny_intrinsics)
    assert (merged / "manifest.jsonl").read_bytes() == (tiny_intrinsics / "manifest.jsonl").read_bytes()
    assert run_gen("inspect", str(merged), "--quiet").returncode == 0


def test_inspect_summarises_and_writes_a_preview_grid(tiny_intrinsics):
    proc = run_gen("inspect", str(tiny_intrinsics), "--json", "--quiet")
    s = json.loads(proc.stdout)
    assert s["complete"] and s["samples"] == 4 and not s["problems"]
    assert set(s["layers"]) == {"normal", "albedo", "reflection", "mask", "material", "depth", "part", "gloss"}
    assert s["layers"]["normal"]["min"] >= -1.001 and s["layers"]["mask"]["max"] == 1.0
    from PIL import Image

    grid = Image.open(s["grid"])  # normal, albedo, reflection, depth, part, gloss under a title band
    assert grid.size == (6 * 64, 14 + 4 * 32)


@pytest.mark.parametrize("args, message", [
    (["--cars", "no_such_car.glb"], "--cars no_such_car.glb: no such model file"),
    (["--cars", "no_such_model"], "'no_such_model' is neither a catalogue model"),
    (["--envmap", "missing.hdr"], "--envmap missing.hdr: no such file"),
    (["--resolution", "512by256"], "--resolution '512by256': expected WIDTHxHEIGHT"),
    (["--resolution", "0x256"], "between 8 and 8192"),
    (["--count", "0"], "Invalid value for '--count'"),
    (["--shard", "3/2"], "--shard '3/2'"),
])
def test_bad_input_gives_a_one_line_error(tmp_path, args, message):
    base = ["intrinsics", "--out", str(tmp_path / "d"), "--count", "2", "--resolution", "64x32", "--quiet"]
    # later options override earlier ones in click, so `args` wins
    proc = run_gen(*base, *args, check=False)
    assert proc.returncode != 0
    err = proc.stderr.strip().splitlines()
    assert err and message in err[-1], proc.stderr
    assert "Traceback" not in proc.stderr


def test_unreadable_envmap_is_rejected(tmp_path):
    fake = tmp_path / "sky.hdr"
    fake.write_bytes(b"this is no image")
    proc = run_gen("intrinsics", "--out", str(tmp_path / "d"), "--count", "1", "--envmap", str(fake), check=False)
    assert proc.returncode != 0 and "not a Radiance HDR file" in proc.stderr


def test_a_folder_of_another_recipe_is_refused_and_kept(tiny_intrinsics, tmp_path):
    import shutil

    out = tmp_path / "keep"
    shutil.copytree(tiny_intrinsics, out)
    before = _files(out)
    proc = run_gen("intrinsics", "--out", str(out), "--count", "4", "--resolution", "64x32", "--seed", "9",
                   "--quiet", check=False)
    assert proc.returncode != 0 and "another recipe" in proc.stderr and "'seed' is 3 there and 9 here" in proc.stderr
    assert _files(out) == before
    # a set from before per-sample noise by frame number is refused with the reason
    info = json.loads((out / "dataset.json").read_text())
    del info["recipe"]["noise"]
    (out / "dataset.json").write_text(json.dumps(info))
    proc = run_gen("intrinsics", "--out", str(out), "--count", "4", "--resolution", "64x32", "--seed", "3",
                   "--quiet", check=False)
    assert proc.returncode != 0 and "older iae-gen" in proc.stderr
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "notes.txt").write_text("mine")
    proc = run_gen("intrinsics", "--out", str(stray), "--count", "1", check=False)
    assert proc.returncode != 0 and "not empty" in proc.stderr and (stray / "notes.txt").read_text() == "mine"


@assets_mark("hdri")
def test_a_real_hdri_environment_renders(tmp_path):
    hdr = SHARED_ASSETS / "hdri" / "potsdamer_platz_1k.hdr"
    out = tmp_path / "hdri"
    run_gen("intrinsics", "--out", str(out), "--count", "2", "--resolution", "64x32", "--envmap", str(hdr), "--quiet")
    rows = read_manifest(out / "manifest.jsonl")
    assert {r["envmap"]["name"] for r in rows} == {"potsdamer_platz_1k.hdr"}
    refl = read_exr(out / rows[0]["file"], ["reflection"])["reflection"]
    assert refl.max() > 0.05


def test_body_normals_are_smooth_not_faceted():
    """Faceted shading shows as runs of identical neighbouring normals with jumps between
    facets; smooth shading as small steps. Measured at 512x256 in a separate Blender
    process, with the same car flat-shaded as the counter-example the check must reject."""
    code = """
import json, numpy as np
from scipy import ndimage
from blender_gen.recipe import Recipe
from blender_gen.render import SampleRenderer
r = SampleRenderer(Recipe(kind='intrinsics', seed=11, width=512, height=256, cars=('sedan_a', 'suv_b')), threads=2)
def steps():
    out = []
    for i in (0, 1, 4, 5):
        L, _ = r.render_layers(i)
        body = ndimage.binary_erosion(L['material'][..., 0] == 19, iterations=2)
        n = L['normal']
        pair = body[:, 1:] & body[:, :-1]
        out.append(np.degrees(np.arccos(np.clip(np.sum(n[:, 1:] * n[:, :-1], -1)[pair], -1, 1))))
    s = np.concatenate(out)
    return [float((s < 0.05).mean()), float(np.percentile(s, 99)), int(s.size)]
res = {'smooth': steps()}
for car in r.cars.values():
    for o in car.objects.values():
        o.data.shade_flat()
res['flat'] = steps()
res['scratch'] = r._scratch  # never closed: the interpreter's exit must remove it
print(json.dumps(res))
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    same, p99, n = res["smooth"]
    assert n > 2000
    assert same < 0.35 and p99 < 20.0, res
    flat_same, flat_p99, _ = res["flat"]
    assert flat_same > 0.5 or flat_p99 > 25.0, f"the check must reject faceted normals: {res}"
    assert not Path(res["scratch"]).exists(), "a renderer's scratch file outlived its process"


def test_scratch_files_of_killed_renderers_are_swept_and_live_ones_kept(renderer, tmp_path):
    from blender_gen.render import SCRATCH_PREFIX, STALE_SCRATCH_S, sweep_stale_scratch

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    names = {"dead, old": f"{SCRATCH_PREFIX}{dead}_a.exr", "dead, just written": f"{SCRATCH_PREFIX}{dead}_b.exr",
             "live, old": f"{SCRATCH_PREFIX}{os.getpid()}_c.exr", "not ours": f"{dead}_d.exr"}
    old = time.time() - STALE_SCRATCH_S - 60
    for what, name in names.items():
        (tmp_path / name).write_bytes(b"x")
        if what != "dead, just written":
            os.utime(tmp_path / name, (old, old))
    assert sweep_stale_scratch(str(tmp_path)) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(v for k, v in names.items() if k != "dead, old")
    assert Path(renderer._scratch).name.startswith(f"{SCRATCH_PREFIX}{os.getpid()}_")
