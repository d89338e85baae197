"""The paper's human study (its Table 2): "which of the two images looks more like a real photo?"

`build_study` writes one self-contained HTML page (images embedded) with randomised pairs of
method A against method B and, given real photos, each method against a real photo (the
fooling rate). Answers stay in the browser (localStorage, so a reload resumes) and are exported
as a JSON file that carries everything the summary needs; `summarise` pools answer files of one
study into preference ratios with Wilson 95% intervals.
"""
from __future__ import annotations

import base64
import hashlib
import html
import io
import json
import math
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from blender_gen.dataset import DatasetError, atomic_write_bytes
from train.data import image_files, read_photo

SCHEMA = "iae-ab-study/1"
KINDS = {"AB": ("A", "B"), "AR": ("A", "real"), "BR": ("B", "real")}


class StudyError(ValueError):
    """A study that cannot be built or an answer file that cannot be used (names the file/option)."""


def list_images(folder: Path, option: str) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise StudyError(f"{option} {folder}: no such folder of images")
    files = image_files(folder)
    if not files:
        raise StudyError(f"{option} {folder}: no .png/.jpg images found")
    return files


def _data_uri(path: Path, height: int | None) -> str:
    """Every image re-encoded the same way (JPEG, quality 92) so the file format is never a tell."""
    try:
        img = Image.fromarray((read_photo(path) * 255.0 + 0.5).astype(np.uint8))
    except DatasetError as exc:
        raise StudyError(str(exc)) from None
    if height and img.height != height:
        img = img.resize((max(1, round(img.width * height / img.height)), height), Image.LANCZOS)
    buf = io.BytesIO()
    img.save(buf, "JPEG", quality=92)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


@dataclass(frozen=True)
class Pair:
    id: int
    kind: str  # AB, AR or BR
    left: str  # "A", "B" or "real"
    right: str
    left_file: str
    right_file: str


def make_pairs(a: list[Path], b: list[Path], real: list[Path] | None, n: int, seed: int) -> list[Pair]:
    """n pairs of each kind, shuffled, sides drawn at random.

    When A and B share file names (two renderers of the same intrinsics) an A-vs-B pair shows the
    same scene by both, so content never decides the vote.
    """
    rng = random.Random(seed)
    by_name_b = {p.name: p for p in b}
    shared = [p for p in a if p.name in by_name_b]
    plan: list[tuple[str, Path, Path]] = []
    if shared:
        picks = rng.sample(shared, n) if n <= len(shared) else [rng.choice(shared) for _ in range(n)]
        plan += [("AB", p, by_name_b[p.name]) for p in picks]
    else:
        plan += [("AB", rng.choice(a), rng.choice(b)) for _ in range(n)]
    if real:
        plan += [("AR", rng.choice(a), rng.choice(real)) for _ in range(n)]
        plan += [("BR", rng.choice(b), rng.choice(real)) for _ in range(n)]
    rng.shuffle(plan)
    pairs = []
    for i, (kind, first, second) in enumerate(plan):
        names = KINDS[kind]
        files = (first, second)
        order = (0, 1) if rng.random() < 0.5 else (1, 0)
        pairs.append(Pair(i, kind, names[order[0]], names[order[1]], str(files[order[0]]), str(files[order[1]])))
    return pairs


def build_study(a: Path, b: Path, out: Path, pairs: int, real: Path | None = None, seed: int = 0,
                label_a: str = "A", label_b: str = "B", height: int | None = 256) -> Path:
    """Write OUT/study.html (self-contained) and OUT/study.json (the key, for the record)."""
    files_a, files_b = list_images(a, "--a"), list_images(b, "--b")
    files_real = list_images(real, "--real") if real else None
    names_b = {p.name for p in files_b}
    shared = sum(p.name in names_b for p in files_a)
    limits = {"A-vs-B scenes": shared or len(files_a) * len(files_b)}
    if files_real:
        limits.update({"A-vs-photo pairs": len(files_a) * len(files_real),
                       "B-vs-photo pairs": len(files_b) * len(files_real)})
    what, most = min(limits.items(), key=lambda t: t[1])
    if pairs > most:  # more would only repeat pairs
        raise StudyError(f"--pairs {pairs}: the images give only {most} distinct {what}; choose at most {most}")
    plan = make_pairs(files_a, files_b, files_real, pairs, seed)
    uris: dict[str, str] = {}
    for p in plan:
        for f in (p.left_file, p.right_file):
            if f not in uris:
                uris[f] = _data_uri(Path(f), height)
    images = {f: k for k, f in enumerate(uris)}
    study_id = hashlib.sha256(json.dumps([[p.left_file, p.right_file, p.left] for p in plan]).encode()).hexdigest()[:16]
    key = {"schema": SCHEMA, "study": study_id, "labels": {"A": label_a, "B": label_b, "real": "real photo"},
           "sources": {"A": str(Path(a).resolve()), "B": str(Path(b).resolve()),
                       "real": str(Path(real).resolve()) if real else None},
           "seed": seed, "pairs_per_kind": pairs,
           "pairs": [{"pair": p.id, "kind": p.kind, "left": p.left, "right": p.right, "left_image": images[p.left_file],
                      "right_image": images[p.right_file], "left_file": p.left_file, "right_file": p.right_file}
                     for p in plan]}
    page_data = {"schema": SCHEMA, "study": study_id, "labels": key["labels"], "images": list(uris.values()),
                 "pairs": [{k: v for k, v in q.items() if not k.endswith("_file")} for q in key["pairs"]]}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "study.json", json.dumps(key, indent=1).encode())
    # The title first, the data last: nothing inside the data (labels are user text) is ever read
    # as a placeholder. In the data, <, > and & are JSON escapes, so no label can end the script
    # element or open an HTML comment inside it ('</script>', '<!--').
    data = json.dumps(page_data).replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")
    page = _PAGE.replace("__TITLE__", html.escape(f"Which looks more like a real photo? ({len(plan)} pairs)"))
    page = page.replace("__DATA__", data)
    atomic_write_bytes(out / "study.html", page.encode())
    return out / "study.html"


# ------------------------------------------------------------------------------ summary
def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a proportion k / n (95% by default); (0, 1) when n = 0."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def _read_json(path: Path, missing: str, malformed: str):
    """A JSON file, or a one-line StudyError: `missing` when absent, `malformed` (plus the parser's
    reason) when it is not JSON."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise StudyError(missing) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StudyError(f"{malformed} ({exc})") from None


def read_key(path: Path) -> dict:
    """The study's own key (`study.json`, written by `ab-study`): its id, labels and pairs."""
    path = Path(path)
    key = _read_json(path, f"--study {path}: no such file (the study.json that `ab-study` wrote)",
                     f"--study {path}: not a JSON study key")
    ok = isinstance(key, dict) and key.get("schema") == SCHEMA and isinstance(key.get("study"), str) \
        and isinstance(key.get("labels"), dict) and isinstance(key.get("pairs"), list)
    if ok:
        ok = all(isinstance(key["labels"].get(k), str) for k in ("A", "B", "real")) and all(
            isinstance(p, dict) and isinstance(p.get("pair"), int) and p.get("kind") in KINDS
            and {p.get("left"), p.get("right")} == set(KINDS[p["kind"]]) for p in key["pairs"])
    if not ok:
        raise StudyError(f"--study {path}: not the study.json of `iae-eval ab-study` (schema {SCHEMA})")
    return key


def read_answers(path: Path, key: dict) -> dict:
    """One participant's answers, checked against the study's key: every answer names a pair of
    the study, its kind and one of its two sides; each pair is answered at most once."""
    path = Path(path)
    data = _read_json(path, f"{path}: no such answer file", f"{path}: not a JSON answer file")
    if not isinstance(data, dict) or data.get("schema") != SCHEMA or not isinstance(data.get("answers"), list):
        raise StudyError(f"{path}: not an answer file of `iae-eval ab-study` (expected schema {SCHEMA})")
    if "study" not in data:
        raise StudyError(f"{path}: 'study' missing: an answer file names the study it answers")
    if data.get("study") != key["study"]:
        raise StudyError(f"{path}: answers to study {str(data.get('study'))[:40]!r}, not {key['study']!r} "
                         "(the --study key); summarise one study at a time")
    if not isinstance(data.get("participant", ""), str):
        raise StudyError(f"{path}: 'participant' must be a string")
    pairs = {p["pair"]: p for p in key["pairs"]}
    seen: set[int] = set()
    for i, ans in enumerate(data["answers"]):
        where = f"{path}: answer {i}"
        if not isinstance(ans, dict):
            raise StudyError(f"{where} is not a JSON object ({json.dumps(ans)[:80]})")
        pair = ans.get("pair")
        if not isinstance(pair, int) or isinstance(pair, bool):
            raise StudyError(f"{where}: 'pair' must be a pair number of this study, got {json.dumps(pair)[:40]}")
        p = pairs.get(pair)
        if p is None:
            raise StudyError(f"{where}: pair {pair} is not in this study (it has {len(pairs)} pairs); "
                             "answers for pairs the study does not have are refused")
        if ans.get("kind") != p["kind"]:
            raise StudyError(f"{where}: 'kind' is {json.dumps(ans.get('kind'))[:40]}, but pair {pair} is a "
                             f"{p['kind']!r} comparison")
        if ans.get("chosen") not in (p["left"], p["right"]):
            raise StudyError(f"{where}: 'chosen' is {json.dumps(ans.get('chosen'))[:40]}, but pair {pair} shows "
                             f"{p['left']!r} and {p['right']!r}")
        if p["pair"] in seen:
            raise StudyError(f"{path}: pair {p['pair']} is answered twice; one answer per participant and pair")
        seen.add(p["pair"])
    return data


def summarise(paths: list[Path], study: Path) -> dict:
    """Pool answer files of one study: per comparison, how often the first of the two was chosen.

    Labels come from the study's key, never from answer files (participants can edit those); a
    file given twice, or two files of one named participant, are refused.
    """
    if not paths:
        raise StudyError("no answer files given")
    key = read_key(study)
    files = [read_answers(p, key) for p in paths]
    digests: dict[str, Path] = {}
    names: dict[str, Path] = {}
    for p, f in zip(paths, files):
        d = hashlib.sha256(json.dumps(f["answers"], sort_keys=True).encode()).hexdigest()
        if d in digests:
            raise StudyError(f"{p}: the same answers as {digests[d]}; give each participant's file once")
        digests[d] = p
        who = (f.get("participant") or "").strip()
        if who and who in names:
            raise StudyError(f"{p}: participant {who!r} already answered in {names[who]}; one file per participant")
        if who:
            names[who] = p
    labels = key["labels"]
    rows = []
    for kind, (first, second) in KINDS.items():
        answers = [a for f in files for a in f["answers"] if a["kind"] == kind]
        if not answers:
            continue
        k = sum(a["chosen"] == first for a in answers)
        lo, hi = wilson(k, len(answers))
        per = [sum(a["chosen"] == first for a in f["answers"] if a["kind"] == kind) /
               max(1, sum(a["kind"] == kind for a in f["answers"])) for f in files]
        rows.append({"comparison": f"{labels[first]} vs {labels[second]}", "kind": kind, "chosen": labels[first],
                     "k": k, "n": len(answers), "ratio": k / len(answers), "ci95": [lo, hi],
                     "per_participant": per})
    return {"study": key["study"], "participants": [f.get("participant") or "(anonymous)" for f in files],
            "files": [str(p) for p in paths], "rows": rows}


def format_summary(s: dict) -> str:
    lines = [f"study {s['study']}: {len(s['files'])} answer file(s) ({', '.join(s['participants'])})",
             f"{'comparison':<44}{'chosen as more real':>24}{'95% CI (Wilson)':>18}{'answers':>9}"]
    for r in s["rows"]:
        lo, hi = r["ci95"]
        chosen = f"{r['chosen']} {100 * r['ratio']:.1f}%"
        ci = f"[{100 * lo:.1f}, {100 * hi:.1f}]"
        lines.append(f"{r['comparison']:<44}{chosen:>24}{ci:>18}{r['n']:>9}")
    return "\n".join(lines)


_PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<style>
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1400px;color:#222}
#pair{display:flex;gap:1em;justify-content:center}
#pair figure{margin:0;text-align:center}
#pair img{max-width:100%;height:auto;border:1px solid #ccc;display:block}
button{font-size:1.1em;margin-top:.5em;padding:.4em 1.2em;cursor:pointer}
#status{margin:.8em 0;font-weight:bold}
.hidden{display:none}
</style></head><body>
<h1>Which image looks more like a real photo?</h1>
<p>Look at both images and click the one that looks more like a real photograph (keys: &larr; / &rarr;).
Your answers stay in this browser; when you are done, download them and send the file back.</p>
<p><label>Your name or initials (optional): <input id="participant" size="20"></label></p>
<div id="status"></div>
<div id="pair">
 <figure><img id="left" alt="left image"><button id="pick-left">This one (&larr;)</button></figure>
 <figure><img id="right" alt="right image"><button id="pick-right">This one (&rarr;)</button></figure>
</div>
<p id="done" class="hidden">All pairs answered, thank you. <button id="download">Download answers (JSON)</button></p>
<p><button id="restart">Start again (forgets the answers in this browser)</button></p>
<pre id="export" class="hidden"></pre>
<div id="selfcheck" class="hidden"></div>
<script id="study-data" type="application/json">__DATA__</script>
<script>
"use strict";
const errors = [];
window.addEventListener("error", e => errors.push(String(e.message)));
const S = JSON.parse(document.getElementById("study-data").textContent);
const storeKey = "iae-ab-" + S.study;
let state = {answers: [], participant: ""};
function load() { try { const s = localStorage.getItem(storeKey); if (s) state = JSON.parse(s); } catch (e) {} }
function save() { try { localStorage.setItem(storeKey, JSON.stringify(state)); } catch (e) {} }
let shownAt = 0;
function show() {
  const i = state.answers.length, n = S.pairs.length;
  document.getElementById("status").textContent = i < n ? `Pair ${i + 1} of ${n}` : `${n} of ${n} answered`;
  document.getElementById("pair").classList.toggle("hidden", i >= n);
  document.getElementById("done").classList.toggle("hidden", i < n);
  if (i < n) {
    document.getElementById("left").src = S.images[S.pairs[i].left_image];
    document.getElementById("right").src = S.images[S.pairs[i].right_image];
    shownAt = performance.now();
  }
}
function pick(side) {
  const i = state.answers.length;
  if (i >= S.pairs.length) return;
  const p = S.pairs[i];
  state.answers.push({pair: p.pair, kind: p.kind, left: p.left, right: p.right, choice: side,
                      chosen: side === "left" ? p.left : p.right, ms: Math.round(performance.now() - shownAt)});
  save(); show();
}
function exported() {
  state.participant = document.getElementById("participant").value;
  return {schema: S.schema, study: S.study, labels: S.labels, participant: state.participant,
          created: new Date().toISOString(), total_pairs: S.pairs.length, answers: state.answers};
}
function download() {
  const blob = new Blob([JSON.stringify(exported(), null, 1)], {type: "application/json"});
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = `answers-${S.study}-${(state.participant || "anonymous").replace(/[^A-Za-z0-9_-]/g, "_")}.json`;
  a.click();
}
document.getElementById("pick-left").addEventListener("click", () => pick("left"));
document.getElementById("pick-right").addEventListener("click", () => pick("right"));
document.getElementById("download").addEventListener("click", download);
document.getElementById("restart").addEventListener("click", () => {
  if (location.hash.startsWith("#simulate=") || confirm("Forget all answers?")) { state = {answers: [], participant: ""}; save(); show(); }
});
document.getElementById("participant").addEventListener("change", e => { state.participant = e.target.value; save(); });
document.addEventListener("keydown", e => { if (e.key === "ArrowLeft") pick("left"); if (e.key === "ArrowRight") pick("right"); });
load();
document.getElementById("participant").value = state.participant || "";
show();
// Test hook: "#simulate=LRRL..." clicks the buttons in that order from a fresh start and shows
// the JSON the download button would save (used by the headless-browser test).
if (location.hash.startsWith("#simulate=")) {
  document.getElementById("restart").click();
  document.getElementById("participant").value = "simulated";
  for (const c of location.hash.slice(10)) document.getElementById(c === "L" ? "pick-left" : "pick-right").click();
  const ex = document.getElementById("export");
  ex.textContent = JSON.stringify(exported());
  ex.classList.remove("hidden");
}
window.addEventListener("load", () => {
  const imgs = [...document.images].filter(i => i.getAttribute("src"));
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  document.getElementById("selfcheck").textContent = `images=${imgs.length} broken=${broken} errors=${errors.length}`;
});
</script></body></html>
"""
