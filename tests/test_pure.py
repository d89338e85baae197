"""Blender-free parts: material table, catalogue geometry, cameras, env lookup, format."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from blender_gen.camera import CameraRanges, euler_xyz_deg, look_at, project, sample_camera
from blender_gen.cars import CATEGORIES, PARTS, build_car, load_catalogue, load_part_materials, select_cars
from blender_gen.conversions import from_network, linear_to_srgb, srgb_to_linear, to_network
from blender_gen.dataset import read_exr, read_manifest, write_exr
from blender_gen import envmap
from blender_gen.envmap import cached_procedural_sky, direction_to_uv, procedural_sky, sample_equirect, uv_to_direction
from blender_gen.materials import N_PAINTS, N_PART_MATERIALS, load_materials


def test_material_table_has_the_papers_counts():
    t = load_materials()
    assert len(t.parts) == N_PART_MATERIALS == 18
    assert len(t.paints) == N_PAINTS == 15
    assert sorted(m.id for m in t.parts.values()) == list(range(1, 19))
    for m in list(t.parts.values()) + list(t.paints.values()):
        assert all(0.0 <= c <= 1.0 for c in m.albedo) and 0.0 <= m.gloss <= 1.0


def test_bad_material_table_names_file_and_field(tmp_path):
    bad = tmp_path / "m.toml"
    bad.write_text('[[part]]\nname = "x"\ncolor = "red"\ngloss = 0.5\n')
    with pytest.raises(ValueError, match=r"m\.toml.*color.*sRGB"):
        load_materials(bad)


def test_every_part_maps_to_a_known_material():
    table = load_materials()
    mapping, tinted = load_part_materials()
    for part in PARTS:
        assert mapping[part] == "paint" or mapping[part] in table.parts
    assert tinted in table.parts
    used = set(mapping.values()) | {tinted}
    assert used - {"paint"} == set(table.parts), "every one of the 18 part materials is used by some part"


def test_catalogue_covers_six_categories_and_has_a_heldout_split():
    cat = load_catalogue()
    assert len(cat) >= 28
    assert {c.category for c in cat.values()} == set(CATEGORIES)
    for split in ("train", "heldout"):
        assert {c.category for c in select_cars(cat, f"procedural:{split}")} == set(CATEGORIES)
    with pytest.raises(ValueError, match="nope"):
        select_cars(cat, "nope")


def test_car_geometry_is_deterministic_grounded_and_sized():
    cat = load_catalogue()
    for spec in cat.values():
        parts = build_car(spec)
        pts = np.concatenate([m.verts for m in parts.values()])
        assert abs(pts[:, 2].min()) < 0.01, f"{spec.name}: tyres touch the ground"
        length = pts[:, 0].max() - pts[:, 0].min()
        assert abs(length - spec.length) < 0.35, f"{spec.name}: length {length:.2f} vs {spec.length}"
        assert pts[:, 2].max() <= spec.height + 0.1
        for needed in ("body", "windshield", "window_side", "window_rear", "tyres", "rims", "headlights",
                       "tail_lights", "grille", "bumper_front", "bumper_rear", "mirrors", "licence_plates",
                       "door_handles", "underbody"):
            assert needed in parts, f"{spec.name} lacks {needed}"
    a, b = build_car(cat["sedan_a"]), build_car(cat["sedan_a"])
    assert all(np.array_equal(a[k].verts, b[k].verts) for k in a)


def test_camera_constraints_hold_over_many_draws():
    parts = build_car(load_catalogue()["van_b"])
    pts = np.concatenate([m.verts for m in parts.values()])[::5]
    ranges = CameraRanges()
    rng = np.random.default_rng(0)
    for _ in range(400):
        pose = sample_camera(rng, pts, 512, 256, ranges)
        loc = np.array(pose.location)
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))  # the car's centre (bounding box)
        assert np.hypot(*(loc[:2] - centre[:2])) <= ranges.radius_max + 1e-9
        assert ranges.height_min <= loc[2] <= ranges.height_max
        assert ranges.focal_min <= pose.focal_length <= ranges.focal_max
        xy, depth = project(pts, pose, 512, 256)
        assert (depth > 0).all()
        assert xy[:, 0].min() >= 0 and xy[:, 0].max() <= 512 and xy[:, 1].min() >= 0 and xy[:, 1].max() <= 256
        area = np.ptp(xy[:, 0]) * np.ptp(xy[:, 1])
        assert area >= ranges.min_coverage * 512 * 256
        # looking at the car: the look-at target projects near the image centre
        txy, _ = project(np.array([pose.target]), pose, 512, 256)
        assert np.allclose(txy[0], [256, 128], atol=1e-6)


def test_camera_sampler_fails_clearly_when_impossible():
    pts = np.concatenate([m.verts for m in build_car(load_catalogue()["van_b"]).values()])
    with pytest.raises(ValueError, match="no valid camera"):
        sample_camera(np.random.default_rng(0), pts, 512, 256,
                      CameraRanges(radius_min=0.5, radius_max=1.0, max_tries=50))


def test_look_at_and_euler_round_trip():
    m = look_at(np.array([3.0, -4.0, 1.5]), np.array([0.0, 0.0, 0.7]))
    assert np.allclose(m.T @ m, np.eye(3), atol=1e-12)
    x, y, z = np.deg2rad(euler_xyz_deg(m))
    rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    assert np.allclose(rz @ ry @ rx, m, atol=1e-9)


def test_equirect_mapping_round_trip_and_convention():
    u = np.random.default_rng(1).random((100,))
    v = np.random.default_rng(2).uniform(0.05, 0.95, (100,))
    uu, vv = direction_to_uv(uv_to_direction(u, v))
    assert np.allclose(uu % 1, u, atol=1e-9) and np.allclose(vv, v, atol=1e-9)
    # Blender: +X at the image centre, the zenith at the top
    assert np.allclose(direction_to_uv(np.array([1.0, 0, 0])), (0.5, 0.5))
    assert np.isclose(direction_to_uv(np.array([0, 0, 1.0]))[1], 1.0)
    env = np.zeros((8, 16, 3), np.float32)
    env[0] = 5.0  # top row only
    assert sample_equirect(env, np.array([0, 0, 1.0]))[0] == pytest.approx(5.0)
    assert sample_equirect(env, np.array([0, 0, -1.0]))[0] == pytest.approx(0.0)


def test_procedural_sky_is_hdr_and_deterministic():
    a, b = procedural_sky(3, 256, 128), procedural_sky(3, 256, 128)
    assert np.array_equal(a, b)
    assert a.max() > 50.0 and a.min() >= 0.0, "a sun far brighter than the sky"
    assert not np.array_equal(a, procedural_sky(4, 256, 128))


def test_cached_sky_is_the_built_sky_bit_for_bit_and_a_broken_cache_file_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("IAE_CACHE_DIR", str(tmp_path / "cache"))
    built = procedural_sky(5, 64, 32)
    first = cached_procedural_sky(5, 64, 32)  # builds and writes
    (file,) = (tmp_path / "cache" / "skies").glob("sky5_64x32_*.npy")
    assert np.array_equal(first, built) and first.dtype == np.float32
    calls = []
    monkeypatch.setattr(envmap, "procedural_sky", lambda *a: calls.append(a) or built)
    assert np.array_equal(cached_procedural_sky(5, 64, 32), built) and not calls  # read, not rebuilt
    file.write_bytes(file.read_bytes()[:100])  # a truncated file (a writer killed mid-way never leaves one)
    assert np.array_equal(cached_procedural_sky(5, 64, 32), built) and len(calls) == 1
    assert np.array_equal(np.load(file), built)  # rewritten whole
    # no usable cache folder (a file in its place, or turned off): the sky is built every time
    monkeypatch.setenv("IAE_CACHE_DIR", str(file))
    assert np.array_equal(cached_procedural_sky(5, 64, 32), built) and len(calls) == 2
    monkeypatch.setenv("IAE_CACHE_DIR", "none")
    assert envmap.sky_cache_dir() is None and np.array_equal(cached_procedural_sky(5, 64, 32), built)
    assert not list((tmp_path / "cache" / "skies").glob(".*.tmp"))
    # a writer killed before its rename leaves a temporary; the next build removes it, not a live one's
    monkeypatch.setenv("IAE_CACHE_DIR", str(tmp_path / "cache"))
    dead = file.with_name(f".{file.name}.999999999.tmp")
    live = file.with_name(f".{file.name}.{os.getppid()}.tmp")  # a live process other than this writer
    dead.write_bytes(b"partial"), live.write_bytes(b"partial")
    file.unlink()
    assert np.array_equal(cached_procedural_sky(5, 64, 32), built) and file.exists()
    assert not dead.exists() and live.exists()


def test_network_space_conversions():
    x = np.random.default_rng(0).random((4, 4, 3)).astype(np.float32)
    assert np.allclose(from_network("albedo", to_network("albedo", x)), x, atol=1e-5)
    assert to_network("albedo", np.full((1, 1, 3), 7.0)).max() == pytest.approx(1.0)  # HDR clips
    assert np.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)
    n = np.array([[[0.0, 0.6, 0.8]]], np.float32)
    assert np.array_equal(to_network("normal", n), n)
    with pytest.raises(ValueError):
        to_network("depth", n)


def test_srgb_transfer_functions_equal_colour_science_bit_for_bit():
    import colour

    knees = [0.0031308, 0.0031308 * 12.92, 0.04045]
    x = np.concatenate([np.linspace(-0.5, 1.5, 20001), np.nextafter(knees, 0), knees, np.nextafter(knees, 1)])
    assert np.array_equal(srgb_to_linear(x), colour.models.eotf_sRGB(x))
    assert np.array_equal(linear_to_srgb(x), colour.models.eotf_inverse_sRGB(np.clip(x, 0, 1)))
    assert np.array_equal(srgb_to_linear(0.2), colour.models.eotf_sRGB(0.2))  # scalars too


def test_exr_round_trip_is_half_float_and_atomic(tmp_path):
    layers = {"normal": np.random.default_rng(0).uniform(-1, 1, (6, 10, 3)), "mask": np.ones((6, 10, 1))}
    p = tmp_path / "s.exr"
    write_exr(p, layers)
    back = read_exr(p)
    assert set(back) == {"normal", "mask"}
    assert np.allclose(back["normal"], layers["normal"], atol=1e-3)
    assert not list(tmp_path.glob(".*tmp*"))


def test_torn_last_manifest_line_is_dropped(tmp_path):
    import json

    from blender_gen.dataset import sample_filename

    row = lambda i: json.dumps({"index": i, "file": sample_filename(i), "sha256": "0" * 64})  # noqa: E731
    m = tmp_path / "manifest.jsonl"
    m.write_text(f'{row(0)}\n{row(1)}\n{{"ind')
    assert [r["index"] for r in read_manifest(m)] == [0, 1]
    m.write_text(f'{row(0)}\n{{"ind\n{row(2)}\n')
    with pytest.raises(ValueError, match="line 2"):
        read_manifest(m)


def test_dimensions_per_category_are_real_world_metres():
    """Every named model's measured size lies within its category's published range
    (data_manifests/car_ranges.toml; 3 cm for bumpers and rounding)."""
    from blender_gen.cars.sampler import load_ranges

    ranges = load_ranges()
    for spec in load_catalogue().values():
        parts = build_car(spec)
        pts = np.concatenate([m.verts for k, m in parts.items() if k != "roof_rails"])
        body = np.concatenate([parts["body"].verts, parts["windshield"].verts])
        r = ranges[spec.category]
        for what, value in (("length", np.ptp(pts[:, 0])), ("width", np.ptp(body[:, 1])), ("height", pts[:, 2].max())):
            lo, hi = r[what]
            assert lo - 0.03 <= value <= hi + 0.03, (spec.name, what, value, (lo, hi))
        assert 1.6 <= np.ptp(pts[:, 1]) <= 2.45, spec.name  # width including mirrors (a 2 m van: 2.3 m)

def test_no_import_circles_between_project_modules():
    """Module A imports B (anywhere in its file, function-level imports included) and B imports A:
    what both use belongs below both. The CLIs are the tops and are left out as importers' targets."""
    import ast

    root = Path(__file__).resolve().parent.parent
    graph: dict[str, set[str]] = {}
    for pkg in ("blender_gen", "train", "eval"):
        for path in (root / pkg).rglob("*.py"):
            mod = ".".join(path.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
            deps = graph.setdefault(mod, set())
            base = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom):
                    if node.level:
                        target = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
                    else:
                        target = node.module or ""
                    names = [target] + [f"{target}.{a.name}" for a in node.names]
                    deps.update(n for n in names if n.split(".")[0] in ("blender_gen", "train", "eval"))
                elif isinstance(node, ast.Import):
                    deps.update(a.name for a in node.names if a.name.split(".")[0] in ("blender_gen", "train", "eval"))
    graph = {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}
    circles = sorted({tuple(sorted((a, b))) for a, deps in graph.items() for b in deps
                      if a in graph.get(b, set()) and not a.endswith("__init__") and "." in a and "." in b
                      and a not in ("blender_gen.cars", "train", "eval", "blender_gen")
                      and b not in ("blender_gen.cars", "train", "eval", "blender_gen")})
    assert not circles, circles


def _affinity() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def test_auto_workers_follow_the_usable_cpus_and_the_work_left(monkeypatch):
    from blender_gen.generate import auto_workers

    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("CPU affinity is a Linux feature")
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(32)))
    assert auto_workers(10_000) == 8  # at most 8 processes, however many CPUs
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {2, 5})  # e.g. under taskset or a cpuset
    assert [auto_workers(n) for n in (0, 1, 8, 9, 2000)] == [1, 1, 1, 2, 2]  # at least 8 samples each


def test_worker_processes_get_disjoint_cpu_groups(monkeypatch):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from blender_gen.generate import cpu_groups, pin_worker, worker_threads

    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("CPU affinity is a Linux feature")
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert cpu_groups(2) == [[0, 1], [2, 3]] and worker_threads(2) == 2
    assert cpu_groups(3) == [[0], [1], [2, 3]]
    assert cpu_groups(1) is None and cpu_groups(5) is None  # one worker keeps every CPU; too many are not pinned
    monkeypatch.setenv("IAE_PIN_WORKERS", "0")
    assert cpu_groups(2) is None
    monkeypatch.undo()
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("needs two CPUs")
    # spawned workers pin themselves in turn, as iae-gen's do, before any Blender thread starts
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(2, mp_context=ctx, initializer=pin_worker, initargs=(cpu_groups(2), ctx.Value("i", 0))) as pool:
        futures = [pool.submit(_affinity) for _ in range(8)]
        seen = {tuple(f.result()) for f in futures}
    assert seen and seen <= set(map(tuple, cpu_groups(2)))  # unpinned, a worker would see every CPU
