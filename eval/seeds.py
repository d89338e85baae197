"""Several seeds of one comparison side by side: per-model tables with every seed's figure and
the paper's orderings, each said to hold on all seeds, on some, or on none.

A seed's comparison may come in parts (`merge`): on a 2-core machine its ten runs take many hours,
so each part reports the runs it finished and the parts are joined afterwards, provided they were
evaluated on the same sets.

Input: the `results.json` of `iae-eval report` (or of `reproduce`, `OUT/report/`) per seed, for the
same models. Single runs here move by several degrees between evaluations, so an ordering is only
called held when it holds on every seed, and each comes with its margins per seed and the spread
of the full model across seeds to compare them with.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from .paper_figures import paper_value

FULL = "Ours (full)"
CONSTANT = "Constant predictor"
# (what, lower is better) per column: Table 3 columns, then Table 1's
COLUMNS = (("normals (deg)", ("dec", "normal_mean_deg")), ("albedo L1", ("dec", "albedo_l1_srgb255")),
           ("reflection L1", ("dec", "reflection_l1_srgb255")), ("FID", ("fid", "fid")), ("KID x100", ("fid", "kid")))
# The full model ahead of each of these: the paper's orderings where its Tables 1 and 3 have both
# figures (each ordering line says which), and the natural reading of an ablation elsewhere
PAPER_AHEAD_OF = ("Ours, w/o shared discr.", "Ours, w/o decomp. cycle", "Ours, w/o rendering cycle", "Ours, w/o A",
                  "Ours, w/o N", "Ours, w/o F", "CycleGAN", "MUNIT")


@dataclass
class Seeded:
    label: str
    values: dict[str, list[float | None]]  # column -> one value per seed (None: not evaluated)


def _value(entry: dict, where: tuple[str, str]) -> float | None:
    part = entry.get(where[0])
    if not isinstance(part, dict) or part.get(where[1]) is None:
        return None
    v = float(part[where[1]])
    return 100.0 * v if where[1] == "kid" else v


def _run_key(entry: dict) -> tuple | None:
    """What makes two results one run: the checkpoint's content, or (older results) folder and step."""
    if entry.get("checkpoint_sha256"):
        return "sha", entry["checkpoint_sha256"]
    return ("run", str(entry["run"]), str(entry.get("step"))) if entry.get("run") else None


def check_seeds(paths: list[Path], datas: list[dict]) -> None:
    """Refuse inputs that are not distinct seeds of one comparison: the same results twice, one run
    in two inputs (a part beside the merge holding it), one training twice (same seed on the same
    sets), or runs of different budgets (steps, training size, Table-3 set size or resolution)."""
    files = [_results_file(p).resolve() for p in paths]
    for k, f in enumerate(files):
        if f in files[:k]:
            raise ValueError(f"{paths[k]}: named twice; each seed's results once")
    seen: dict[tuple, Path] = {}
    trainings: dict[tuple, Path] = {}
    budget: dict[str, tuple[Path, tuple]] = {}
    for path, data in zip(paths, datas):
        for entry in data.get("runs", []):
            key = _run_key(entry)
            if key is not None and key in seen:
                raise ValueError(f"{path}: run '{entry.get('label')}' ({entry.get('run')}, step {entry.get('step')}) is "
                                 f"also in {seen[key]}; one run's figures would count as two seeds")
            seen[key] = path
            if entry.get("seed") is not None and entry.get("trained_on"):
                t = (entry.get("label"), entry["seed"], tuple(entry["trained_on"]))
                if t in trainings:
                    raise ValueError(f"{path}: '{entry.get('label')}' trained with seed {entry['seed']} on the same sets "
                                     f"as in {trainings[t]}; seeds need distinct training seeds or data")
                trainings[t] = path
            sets = {d.get("role"): d for d in data.get("datasets", [])}
            ev = sets.get("--data", {})
            b = (entry.get("step"), tuple(entry.get("size") or ()), ev.get("count"), tuple(ev.get("resolution") or ()))
            label = str(entry.get("label"))
            if label in budget and budget[label][1] != b:
                def say(x: tuple) -> str:
                    size = "x".join(map(str, x[1])) or "?"
                    res = "x".join(map(str, x[3])) or "?"
                    return f"step {x[0]}, training {size}, {x[2]} Table-3 images at {res}"
                raise ValueError(f"{path}: '{label}' at {say(b)}, but at {say(budget[label][1])} in "
                                 f"{budget[label][0]}; seeds of one comparison share a budget")
            budget.setdefault(label, (path, b))


def load(paths: list[Path]) -> tuple[list[str], dict[str, Seeded]]:
    """Seed names (the folders) and, per model label, its figures per seed, in the first file's order."""
    rows: dict[str, Seeded] = {}
    names = []
    datas = [read_results(p) for p in paths]
    check_seeds(paths, datas)
    for k, (path, data) in enumerate(zip(paths, datas)):
        names.append(_seed_name(_results_file(path)))
        for entry in data.get("runs", []) + data.get("references", []):
            label = entry.get("label")
            if not label:
                continue
            row = rows.setdefault(label, Seeded(label, {c: [None] * len(paths) for c, _ in COLUMNS}))
            for col, where in COLUMNS:
                row.values[col][k] = _value(entry, where)
    return names, rows


# What must agree between the parts of one seed: every field of the evaluation sets but where
# they lay (each part may have its own output folder)
# (results written before sets recorded their resolution and content digest have neither: None on both sides agrees)
_SET_FIELDS = ("kind", "count", "seed", "cars", "envmaps", "resolution", "content_sha256")
_SET_ROLES = ("--data", "--real", "--intrinsics")


def _set_diff(a: dict | None, b: dict) -> list[str]:
    """The fields of _SET_FIELDS in which dataset record `a` (missing: all) differs from `b`."""
    return [k for k in _SET_FIELDS if a is None or a.get(k) != b.get(k)]


def _results_file(path: Path) -> Path:
    """The results.json that `path` names: the file itself or the report folder holding it."""
    return path / "results.json" if path.is_dir() else path


def _seed_name(f: Path) -> str:
    """A seed's name in the tables: its report folder (reproduce's OUT/report: OUT), or the file's
    stem when the results file was renamed (cpu_s21.json: cpu_s21)."""
    folder = f.parent if f.name == "results.json" else f.with_suffix("")
    return folder.parent.name if folder.name == "report" else folder.name


def read_results(path: Path) -> dict:
    """A report's results.json (the file, or the report folder holding it); a one-line error names
    the file when it is missing or not JSON."""
    f = _results_file(path)
    try:
        data = json.loads(f.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{f}: cannot read a report's results.json ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("runs", []), list) or \
            not all(isinstance(r, dict) for r in data.get("runs", []) + data.get("references", [])):
        raise ValueError(f"{f}: not a report's results.json (expected an object with a list of runs)")
    return data


def merge(parts: list[Path]) -> dict:
    """One seed's results.json from several reports of disjoint runs on the same evaluation sets
    (same kind, count, seed, cars and skies; the folders may differ). References (constant
    predictor, albedo copy) come from the first part."""
    if not parts:
        raise ValueError("merge: no reports given")
    datas = [read_results(p) for p in parts]
    first = {d["role"]: d for d in datas[0].get("datasets", []) if d.get("role") in _SET_ROLES}
    missing = [r for r in _SET_ROLES if r not in first]
    if missing:
        raise ValueError(f"{parts[0]}: its results.json names no {', '.join(missing)} set; cannot check the parts agree")
    seen: dict[str, Path] = {}
    runs = []
    trained_on: dict[str, tuple[Path, dict]] = {}  # "training intrinsics" / "real images" -> first seen
    for path, data in zip(parts, datas):
        for d in data.get("datasets", []):  # every run of the seed trained on the same two sets
            kind = next((k for k in ("training intrinsics", "real images") if str(d.get("role", "")).endswith(k)), None)
            if kind is None:
                continue
            where, ref = trained_on.setdefault(kind, (path, d))
            diff = _set_diff(d, ref)
            if diff:
                raise ValueError(f"{path}: {d['role']} differ from {where}'s {ref['role']} in {', '.join(diff)}; "
                                 "parts of one seed must train on the same sets")
        sets = {d["role"]: d for d in data.get("datasets", []) if d.get("role") in _SET_ROLES}
        for role, ref in first.items():
            other = sets.get(role)
            diff = _set_diff(other, ref)
            if diff:
                raise ValueError(f"{path}: its {role} set differs from {parts[0]}'s in {', '.join(diff)}; "
                                 "parts of one seed must be evaluated on the same sets")
        for entry in data.get("runs", []):
            label = entry.get("label")
            if label in seen:
                raise ValueError(f"{path}: run '{label}' is also in {seen[label]}; each run belongs to one part")
            seen[label] = path
            runs.append(entry)
    warnings = sorted({w for d in datas for w in d.get("warnings", [])})
    steps = {str(e.get("step")) for e in runs}
    if len(steps) > 1:
        warnings.append("the joined runs were evaluated at different steps: " +
                        ", ".join(f"{e['label']} {e.get('step')}" for e in runs))
    return {"runs": runs, "references": datas[0].get("references", []), "datasets": datas[0].get("datasets", []),
            "warnings": warnings,
            "parts": [{"path": str(p), "datasets": d.get("datasets", [])} for p, d in zip(parts, datas)]}


def _fmt(vals: list[float | None], digits: int = 1) -> str:
    return " / ".join("-" if v is None else f"{v:.{digits}f}" for v in vals)


def table(names: list[str], rows: dict[str, Seeded]) -> str:
    head = "| model | " + " | ".join(c for c, _ in COLUMNS) + " |"
    lines = [f"Seeds, in this order: {', '.join(names)}", "", head, "|---" * (len(COLUMNS) + 1) + "|"]
    for label, row in rows.items():
        lines.append(f"| {label} | " + " | ".join(_fmt(row.values[c]) for c, _ in COLUMNS) + " |")
    return "\n".join(lines)


def orderings(rows: dict[str, Seeded]) -> list[str]:
    """One line per (model, column) of the paper's orderings: holds / holds on k of n / fails."""
    if FULL not in rows:
        return [f"no '{FULL}' run in the reports: no orderings to check"]
    full = rows[FULL]
    out = []
    spread = {c: [v for v in full.values[c] if v is not None] for c, _ in COLUMNS}
    spread = {c: v for c, v in spread.items() if len(v) > 1}
    out.append("the full model's spread across seeds (max - min): " + ", ".join(
        f"{c} {max(v) - min(v):.1f}" for c, v in spread.items()) if spread else
        "one seed: no spread yet, so no ordering below is settled")
    for other in (CONSTANT,) + PAPER_AHEAD_OF:
        if other not in rows:
            continue
        for col, _ in COLUMNS:
            pairs = [(a, b) for a, b in zip(full.values[col], rows[other].values[col]) if a is not None and b is not None]
            if not pairs:
                continue
            margins = [b - a for a, b in pairs]  # positive: the full model is better (lower)
            wins = sum(m > 0 for m in margins)
            verdict = "holds" if wins == len(pairs) else "fails" if wins == 0 else f"holds on {wins} of {len(pairs)} seeds"
            out.append(f"full better than {other} on {col}: {verdict} (margins {_fmt(margins)}){_paper_says(other, col)}")
    return out


def _paper_says(other: str, col: str) -> str:
    """Whether the paper measured this ordering: its two figures, or that it has none."""
    if other == CONSTANT:
        return ""  # not a paper row: the bar a model must clear to have learned anything
    ours, theirs = paper_value(FULL, col), paper_value(other, col)
    if ours is None or theirs is None:
        return "; the paper has no figure for it"
    return f"; paper: {ours:g} against {theirs:g}" + ("" if ours < theirs else ", the full model not ahead there either")


def compare(paths: list[Path]) -> str:
    names, rows = load(paths)
    return table(names, rows) + "\n\n" + "\n".join(f"- {line}" for line in orderings(rows)) + "\n"
