"""Dataset generation: resume, worker processes, shards and merging (no bpy here).

The parent process owns dataset.json and manifest.jsonl; Blender runs in-process for one
worker and in `spawn`ed processes for several. Results come back in sample order
(`imap`), so the manifest of a fresh run is the same whatever the number of workers.
"""
from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from importlib import metadata
import os
import platform
import shutil
import sys
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from .dataset import (MAX_INDEX, DatasetError, DatasetWriter, atomic_target, atomic_write_json,
                      folder_is_empty, lock_holder, locked_folder, read_info, read_manifest, reading_folder,
                      remove_temporaries, verify_rows, write_manifest)
from .cars.spec import PARTS
from .recipe import Recipe, identity_diff


class GenerationError(ValueError):
    """Bad input for a generation run; the message names the option or file."""


def parse_shard(text: str | None) -> tuple[int, int]:
    if not text:
        return 0, 1
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise GenerationError(f"--shard {text!r}: expected I/N with integers, e.g. 0/4") from None
    if n < 1 or not 0 <= i < n:
        raise GenerationError(f"--shard {text!r}: expected 0 <= I < N")
    return i, n


def software_versions() -> dict:
    """Package versions from their metadata: importing bpy here would put Blender's script
    folders on sys.path, which spawned workers inherit and then cannot import bpy."""
    versions = {"python": platform.python_version()}
    for dist in ("bpy", "numpy", "OpenEXR", "intrinsic-autoencoders"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    return versions


def prepare_output(out: Path, recipe: Recipe, count: int, shard: tuple[int, int]) -> tuple[DatasetWriter, list[dict]]:
    """Create or re-open `out`; refuse a folder that holds another recipe or other files.

    Returns the dataset's writer and the manifest rows whose files verify.
    """
    out = Path(out)
    identity = recipe.identity()
    if out.exists() and not out.is_dir():
        raise GenerationError(f"--out {out}: exists and is not a directory")
    if (out / "dataset.json").exists():
        info = read_info(out)
        diff = identity_diff(info.get("recipe", {}), identity)
        if diff:
            raise GenerationError(f"--out {out} holds a dataset made with another recipe ({diff}); "
                                  "choose another --out or repeat the original options")
        if tuple(info.get("shard", [0, 1])) != shard:
            raise GenerationError(f"--out {out} holds shard {info.get('shard')}, not {list(shard)}")
    elif out.exists() and not folder_is_empty(out):
        raise GenerationError(f"--out {out}: folder is not empty and holds no dataset.json; refusing to mix files")
    (out / "samples").mkdir(parents=True, exist_ok=True)
    _remove_temporaries(out)  # left by a killed writer
    rows = read_manifest(out / "manifest.jsonl")
    good, bad = verify_rows(out, rows)
    for row, why in bad:
        print(f"redoing sample {row['index']}: {why}", file=sys.stderr)
    writer = DatasetWriter(out, {
        "kind": recipe.kind,
        "resolution": [recipe.width, recipe.height],
        "seed": recipe.seed,
        "count_requested": count,
        "shard": list(shard),
        "software": software_versions(),
        "recipe": identity,
        "layers": list(recipe.layers()),
        **({"parts": ["background", *PARTS]} if "part" in recipe.layers() else {}),  # part index -> name
    }, rows=good)
    return writer, good


# ------------------------------------------------------------------- worker processes
_worker = None


def make_renderer(recipe: Recipe, threads: int = 0):
    """The Blender renderer for the recipe's dataset kind (imports bpy)."""
    if recipe.kind == "intrinsics":
        from .render import SampleRenderer

        return SampleRenderer(recipe, threads)
    if recipe.kind == "pbr":
        from .pbr import PbrRenderer

        return PbrRenderer(recipe, threads)
    raise ValueError(f"unknown dataset kind {recipe.kind!r}")


def die_with_parent(parent: int) -> None:
    """End this process as soon as `parent` is gone (a killed `iae-gen` leaves no workers).

    Linux delivers SIGKILL through PR_SET_PDEATHSIG; a watchdog thread covers other systems
    and the race where the parent died before the request was made.
    """
    import ctypes
    import signal
    import threading

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    if os.getppid() != parent:
        os._exit(1)
    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


class Interrupted(Exception):
    """Ctrl-C or SIGTERM: the sample being rendered was finished and recorded, then the run stopped."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by signal {signum}")
        self.signum = signum


@contextmanager
def _stop_requests():
    """One Ctrl-C (or SIGTERM) asks the run to stop after the sample being rendered; a second stops
    at once. A flag, not an exception: an exception raised inside Blender's render is printed as a
    traceback and swallowed, and the render went on."""
    import signal
    import threading

    state = {"signum": None}
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum, frame) -> None:
        if state["signum"] is not None:
            os._exit(128 + signum)
        state["signum"] = signum
        print("\nstopping after the current sample (Ctrl-C again to stop at once)", file=sys.stderr, flush=True)

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield state
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (taskset, cgroups' cpusets), in order."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux: no affinity, every CPU
        return list(range(os.cpu_count() or 1))


MAX_AUTO_WORKERS = 8  # bounds memory (about 0.6 GiB per worker) and start-up; beyond it workers get more threads
MIN_SAMPLES_PER_WORKER = 8  # a worker's start-up (Blender, scene) costs about as much as a few samples


def auto_workers(todo: int) -> int:
    """`--workers auto`: one Blender process per usable CPU, at most 8, and at least 8 samples
    each, so a short run does not pay for starting processes it hardly uses. Pinned workers with
    one Cycles thread each beat one process with every thread (measured on a 2-core CPU: 16.5
    against 8.5 intrinsics samples/s at 512x256)."""
    by_work = max(1, -(-todo // MIN_SAMPLES_PER_WORKER))
    return max(1, min(len(usable_cpus()), MAX_AUTO_WORKERS, by_work))


def cpu_groups(workers: int) -> list[list[int]] | None:
    """Disjoint sets of the usable CPUs, one per worker process; None for one worker (it keeps every
    CPU) and when there are fewer CPUs than workers. Blender's TBB pool sizes itself from the
    process's CPUs, and an idle TBB worker spins in sched_yield: unpinned, every worker process kept
    a thread busy on a core of its own (measured: one worker with one Cycles thread used 1.9 cores
    at 512x256, pinned 1.0 at the same rate). IAE_PIN_WORKERS=0 leaves them unpinned (to measure
    the difference, or to let a scheduler place them)."""
    cpus = usable_cpus()
    if workers < 2 or workers > len(cpus) or os.environ.get("IAE_PIN_WORKERS", "1") == "0":
        return None
    return [cpus[k * len(cpus) // workers:(k + 1) * len(cpus) // workers] for k in range(workers)]


def worker_threads(workers: int) -> int:
    """Cycles threads per worker process: its share of the usable CPUs."""
    return max(1, len(usable_cpus()) // workers)


def pin_worker(groups: list[list[int]] | None, slot) -> None:
    """Pin this worker process to its CPU group: the k-th worker to start takes group k (a replaced
    worker the next one), counted in the shared integer `slot`. Must run before Blender starts its
    thread pool."""
    if not groups or not hasattr(os, "sched_setaffinity"):
        return
    with slot.get_lock():
        k = slot.value
        slot.value += 1
    os.sched_setaffinity(0, groups[k % len(groups)])


def _init_worker(recipe: Recipe, threads: int, parent: int, groups: list[list[int]] | None = None,
                 slot=None) -> None:
    import signal

    global _worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop (Ctrl-C reaches the group)
    die_with_parent(parent)
    pin_worker(groups, slot)
    _worker = make_renderer(recipe, threads)


def _render_one(args: tuple[int, str]) -> dict:
    index, out = args
    return _worker.render(index, Path(out))


def generate(recipe: Recipe, out: Path, count: int, workers: int | str = 1, shard: str | None = None,
             progress: bool = True) -> dict:
    """Render samples [0, count) of this shard that are not finished yet; returns dataset.json.

    `workers` is a number of Blender processes or "auto" (`auto_workers` of the samples left).

    The folder is locked for the whole run, so a second generator on it fails at once.
    """
    if not 1 <= count <= MAX_INDEX + 1:
        raise GenerationError(f"--count {count}: expected 1 to {MAX_INDEX + 1}")
    if workers != "auto" and (not isinstance(workers, int) or workers < 1):
        raise GenerationError(f"--workers {workers}: expected at least 1, or auto")
    shard_t = parse_shard(shard)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise GenerationError(f"--out {out}: exists and is not a directory")
    if out.exists() and not (out / "dataset.json").exists() and not folder_is_empty(out):
        raise GenerationError(f"--out {out}: folder is not empty and holds no dataset.json; refusing to mix files")
    try:
        intact = _intact(recipe, out, count, shard_t)
        if intact is not None:
            return intact
        with locked_folder(out):
            return _generate_locked(recipe, out, count, workers, shard_t, progress)
    except OSError as exc:  # e.g. the folder cannot be created at all
        raise DatasetError(f"--out {out}: {exc.strerror or exc}" + (f" ({exc.filename})" if exc.filename else "")) from None


def _intact(recipe: Recipe, out: Path, count: int, shard_t: tuple[int, int]) -> dict | None:
    """The info of a finished set that this command would leave as it is, verified under a reader's
    lock: rerunning a command on it writes nothing, so a training that reads the set meanwhile (two
    `reproduce` runs sharing --data) is not refused. None when there is anything to write, repair
    or refuse: the writer's path does that."""
    if not (out / "dataset.json").exists():
        return None
    with reading_folder(out) as held:
        if not held:
            return None
        info = read_info(out)
        identity = legacy_recipe(recipe, out).identity()
        if (identity_diff(info.get("recipe", {}), identity) or tuple(info.get("shard", [0, 1])) != shard_t
                or info.get("complete") is not True or info.get("count_requested") != count):
            return None
        if any(any(d.glob(".*.tmp*")) for d in (out, out / "samples", out / "previews")):
            return None  # a dead writer's temporaries: the writer's path removes them
        rows = read_manifest(out / "manifest.jsonl")
        wanted = {i for i in range(count) if i % shard_t[1] == shard_t[0]}
        if sorted(r.get("index") for r in rows) != sorted(wanted) or verify_rows(out, rows)[1]:
            return None
    return {**info, "_rendered": 0, "_seconds": 0.0}


def _unstarted(out: Path) -> None:
    """Remove what a run that never finished a sample wrote into a folder it found empty, so the
    folder takes a corrected command (e.g. a turntable refused for its --radius)."""
    import shutil

    for name in ("dataset.json", "manifest.jsonl"):
        (out / name).unlink(missing_ok=True)
    for sub in ("samples", "previews"):
        if (out / sub).is_dir() and not any(p.is_file() and not p.name.startswith(".") for p in (out / sub).rglob("*")):
            shutil.rmtree(out / sub, ignore_errors=True)


def legacy_recipe(recipe: Recipe, out: Path) -> Recipe:
    """The recipe as an existing set at `out` was made, so it resumes and extends byte-identically:
    an environment-background set from before the NumPy lookup keeps Cycles' Environment pass, and
    a set from before the extra layers (depth, part, gloss, light passes) keeps the layers it has."""
    if not (out / "dataset.json").exists():
        return recipe
    old = read_info(out).get("recipe", {})
    if not old:
        return recipe
    if recipe.background == "environment" and old.get("background") == "environment" and "environment_pass" not in old:
        recipe = replace(recipe, environment_pass="cycles")
    if tuple(old.get("extra_layers", ())) != recipe.extras():
        recipe = replace(recipe, extra_layers=tuple(old.get("extra_layers", ())))
    return recipe


def _generate_locked(recipe: Recipe, out: Path, count: int, workers: int | str, shard_t: tuple[int, int],
                     progress: bool) -> dict:
    fresh = not (out / "dataset.json").exists()
    recipe = legacy_recipe(recipe, out)
    writer, done_rows = prepare_output(out, recipe, count, shard_t)
    done = {r["index"] for r in done_rows}
    todo = [i for i in range(count) if i % shard_t[1] == shard_t[0] and i not in done]
    if workers == "auto":
        workers = auto_workers(len(todo))
    total = len(done) + len(todo)
    threads = worker_threads(workers)
    bar = tqdm(total=total, initial=len(done), unit="sample", desc=f"{recipe.kind} {out.name}",
               disable=not progress, smoothing=0.1, dynamic_ncols=True)
    started = time.perf_counter()
    rendered = 0

    def finish() -> dict:
        return writer.finish(expected=total)

    stops = _stop_requests()
    stop = stops.__enter__()
    try:
        if todo and workers == 1:
            renderer = make_renderer(recipe, threads)
            try:
                for i in todo:
                    writer.append(renderer.render(i, out))
                    rendered += 1
                    bar.update()
                    if stop["signum"] is not None:
                        raise Interrupted(stop["signum"])
            finally:
                renderer.close()
        elif todo:
            # spawn: a fresh interpreter per worker (bpy must not be forked); the executor
            # fails fast if a worker cannot start, and map() yields results in sample order.
            ctx = mp.get_context("spawn")
            pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                       initargs=(recipe, threads, os.getpid(), cpu_groups(workers), ctx.Value("i", 0)))
            try:
                jobs = [(i, str(out)) for i in todo]
                for row in pool.map(_render_one, jobs, chunksize=recipe.views_per_car):
                    writer.append(row)
                    rendered += 1
                    bar.update()
                    if stop["signum"] is not None:
                        raise Interrupted(stop["signum"])
            except BaseException:
                _stop_pool(pool)  # queued work must not keep running after a failure or Ctrl-C
                _remove_temporaries(out)  # a killed worker's half-written file must not outlive the run
                raise
            pool.shutdown()
    except BaseException:
        bar.close()
        try:  # record what is finished, but never let a second error hide the first
            if fresh and rendered == 0 and not read_manifest(writer.manifest):
                _unstarted(out)
            else:
                finish()
        except Exception:
            pass
        raise
    finally:
        stops.__exit__(None, None, None)
    bar.close()
    info = finish()
    elapsed = time.perf_counter() - started
    info["_rendered"], info["_seconds"] = rendered, elapsed
    return info


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel queued work and end the workers now (shutdown alone waits for running chunks); returns
    once they are gone, so that nothing they were writing can appear afterwards."""
    procs = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.kill()
    for proc in procs:
        proc.join(timeout=10)


def _remove_temporaries(out: Path) -> None:
    """A dataset's temporaries (this process holds the folder's lock: every one is a dead writer's)."""
    remove_temporaries(out, out / "samples", out / "previews")


def merge(out: Path, shards: list[Path], progress: bool = True) -> dict:
    """Join shard folders of one recipe into `out` (files hard-linked where possible).

    Every source row is validated (its `file` must be its own sample's name), so a
    manifest can never make merge read or write outside the folders it was given.
    """
    if not shards:
        raise GenerationError("merge: give at least one shard folder")
    out = Path(out)
    if out.exists() and not folder_is_empty(out):
        raise GenerationError(f"merge: --out {out} is not empty")
    with locked_folder(out):
        for s in shards:  # before anything is written: a refused merge leaves nothing that refuses the rerun
            holder = lock_holder(s)
            if holder is not None:
                raise GenerationError(f"merge: {s} is being written by {holder}; merge once its generator has "
                                      "finished")
            if read_info(s).get("complete") is False:
                raise GenerationError(f"merge: {s} is incomplete (its generator stopped early); rerun it to finish, "
                                      "then merge")
        return _merge_locked(out, shards, progress)


def _merge_locked(out: Path, shards: list[Path], progress: bool) -> dict:
    infos = [read_info(s) for s in shards]
    base = infos[0]
    for s, info in zip(shards[1:], infos[1:]):
        diff = identity_diff(base.get("recipe", {}), info.get("recipe", {}))
        if diff:
            raise GenerationError(f"merge: {s} was made with another recipe than {shards[0]} ({diff})")
    (out / "samples").mkdir(parents=True, exist_ok=True)
    by_index: dict[int, tuple[Path, dict]] = {}
    for s in shards:
        good, bad = verify_rows(s, read_manifest(Path(s) / "manifest.jsonl"))
        if bad:
            raise DatasetError(f"merge: {s}: {len(bad)} sample(s) fail verification, e.g. {bad[0][0]['file']}: {bad[0][1]}")
        for row in good:
            prev = by_index.get(row["index"])
            if prev and prev[1]["sha256"] != row["sha256"]:
                raise DatasetError(f"merge: sample {row['index']} differs between {prev[0]} and {s}")
            by_index[row["index"]] = (Path(s), row)
    for idx in tqdm(sorted(by_index), desc="merge", unit="sample", disable=not progress):
        src_root, row = by_index[idx]
        src, dst = src_root / row["file"], out / row["file"]
        with atomic_target(dst) as tmp:
            try:
                os.link(src, tmp)
            except OSError:
                shutil.copyfile(src, tmp)
    rows = [by_index[i][1] for i in sorted(by_index)]
    write_manifest(out / "manifest.jsonl", rows)
    requested = max(int(i.get("count_requested", 0)) for i in infos)
    missing = [i for i in range(requested) if i not in by_index]
    info = {**base, "shard": [0, 1], "count": len(rows), "count_requested": requested, "complete": not missing,
            "merged_from": [str(s) for s in shards]}
    atomic_write_json(out / "dataset.json", info)
    info["_missing"] = missing
    return info

