"""Several seeds of one comparison side by side: per-model tables with every seed's figure and
the paper's orderings, each said to hold on all seeds, on some, or on none.

Input: the `results.json` of `iae-eval report` (or of `reproduce`, `OUT/report/`) per seed, for the
same models. Single runs here move by several degrees between evaluations, so an ordering is only
called held when it holds on every seed, and each comes with its margins per seed and the spread
of the full model across seeds to compare them with.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

FULL = "Ours (full)"
CONSTANT = "Constant predictor"
# (what, lower is better) per column: Table 3 columns, then Table 1's
COLUMNS = (("normals (deg)", ("dec", "normal_mean_deg")), ("albedo L1", ("dec", "albedo_l1_srgb255")),
           ("reflection L1", ("dec", "reflection_l1_srgb255")), ("FID", ("fid", "fid")), ("KID x100", ("fid", "kid")))
# The paper's orderings (its Tables 1 and 3): the full model ahead of each of these
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


def load(paths: list[Path]) -> tuple[list[str], dict[str, Seeded]]:
    """Seed names (the folders) and, per model label, its figures per seed, in the first file's order."""
    rows: dict[str, Seeded] = {}
    names = []
    for k, path in enumerate(paths):
        f = path / "results.json" if path.is_dir() else path
        try:
            data = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{f}: cannot read a report's results.json ({exc})") from None
        folder = f.parent if f.name == "results.json" else f.with_suffix("")
        names.append(folder.parent.name if folder.name == "report" else folder.name)  # reproduce's OUT/report
        for entry in data.get("runs", []) + data.get("references", []):
            label = entry.get("label")
            if not label:
                continue
            row = rows.setdefault(label, Seeded(label, {c: [None] * len(paths) for c, _ in COLUMNS}))
            for col, where in COLUMNS:
                row.values[col][k] = _value(entry, where)
    return names, rows


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
    out.append("the full model's spread across seeds (max - min): " + ", ".join(
        f"{c} {max(v) - min(v):.1f}" for c, v in spread.items() if len(v) > 1))
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
            out.append(f"full better than {other} on {col}: {verdict} (margins {_fmt(margins)})")
    return out


def compare(paths: list[Path]) -> str:
    names, rows = load(paths)
    return table(names, rows) + "\n\n" + "\n".join(f"- {line}" for line in orderings(rows)) + "\n"
