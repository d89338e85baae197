"""`iae-gen status`: the state of a sharded run, shard by shard, and exactly what to rerun (no bpy).

A shard folder is finished when every sample index i < count with i % N == I has a manifest row
whose file verifies. Rerunning a shard's own command (the same options and `--shard I/N`) renders
only its missing and damaged samples, so the list printed here is the whole repair.
"""
from __future__ import annotations

from pathlib import Path

from .dataset import DatasetError, lock_holder, read_info, read_manifest, verify_rows
from .recipe import identity_diff


def shard_status(folder: Path) -> dict:
    """One shard folder: its shard, state and the sample indices it lacks or holds damaged."""
    folder = Path(folder)
    info = read_info(folder)
    i, n = (int(v) for v in info.get("shard", [0, 1]))
    count = int(info.get("count_requested", info.get("count", 0)))
    good, bad = verify_rows(folder, read_manifest(folder / "manifest.jsonl"))
    have = {r["index"] for r in good}
    failed = sorted({r["index"] for r, _ in bad} - have)
    missing = [k for k in range(i, count, n) if k not in have and k not in failed]
    holder = lock_holder(folder)
    state = ("running" if holder else "complete" if not missing and not failed
             else "stopped" if info.get("complete") is False or failed else "incomplete")
    return {"folder": str(folder), "shard": [i, n], "count": count, "expected": len(range(i, count, n)),
            "done": len(have), "missing": missing, "failed": failed, "state": state, "writer": holder,
            "recipe": info.get("recipe", {}), "kind": info.get("kind")}


def run_status(folders: list[Path]) -> dict:
    """Every shard folder of one run: per-shard status, shard numbers no folder holds, and whether
    the run is ready to merge."""
    if not folders:
        raise DatasetError("status: give the shard folders of one run (e.g. data/part*)")
    shards = [shard_status(f) for f in folders]
    base = shards[0]
    problems = []
    for s in shards[1:]:
        diff = identity_diff(base["recipe"], s["recipe"])
        if diff:
            problems.append(f"{s['folder']}: another recipe than {base['folder']} ({diff})")
        if s["shard"][1] != base["shard"][1] or s["count"] != base["count"]:
            problems.append(f"{s['folder']}: shard {s['shard'][0]}/{s['shard'][1]} of {s['count']} samples, "
                            f"not of the {base['shard'][1]} shards of {base['count']} that {base['folder']} belongs to")
    n = base["shard"][1]
    seen: dict[int, str] = {}
    for s in shards:
        if s["shard"][0] in seen:
            problems.append(f"{s['folder']}: shard {s['shard'][0]}/{n} is also {seen[s['shard'][0]]}")
        seen.setdefault(s["shard"][0], s["folder"])
    absent = [k for k in range(n) if k not in seen]
    ready = not problems and not absent and all(s["state"] == "complete" for s in shards)
    return {"shards": shards, "absent_shards": absent, "problems": problems, "ready_to_merge": ready}


def format_status(st: dict) -> str:
    lines = []
    for s in st["shards"]:
        i, n = s["shard"]
        line = f"{s['folder']}  shard {i}/{n}  {s['done']}/{s['expected']}  {s['state'].upper()}"
        if s["missing"]:
            line += f"  missing {len(s['missing'])}: {_few(s['missing'])}"
        if s["failed"]:
            line += f"  damaged {len(s['failed'])}: {_few(s['failed'])}"
        if s["writer"]:
            line += f"  (written by {s['writer']})"
        elif s["state"] != "complete":
            line += "  -> rerun its command"
        lines.append(line)
    if st["absent_shards"]:
        n = st["shards"][0]["shard"][1]
        lines.append(f"no folder holds shard(s) {', '.join(f'{k}/{n}' for k in st['absent_shards'])}: run them")
    lines += [f"PROBLEM   {p}" for p in st["problems"]]
    rerun = sorted({s["shard"][0] for s in st["shards"] if s["state"] not in ("complete", "running")}
                   | set(st["absent_shards"]))
    if rerun and not st["problems"]:
        n = st["shards"][0]["shard"][1]
        lines.append(f"rerun shard(s) {','.join(map(str, rerun))} of {n} (Slurm: SHARDS={n} sbatch "
                     f"--array={','.join(map(str, rerun))} deploy/slurm/generate.sbatch)")
    lines.append("ready to merge" if st["ready_to_merge"] else "NOT ready to merge")
    return "\n".join(lines)


def _few(indices: list[int], k: int = 8) -> str:
    return ", ".join(map(str, indices[:k])) + (", ..." if len(indices) > k else "")
