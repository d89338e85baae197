"""Automatic part labelling against hand-written rules.

For each of the 7 Kenney models in ../shared/assets/cars3d/ the faces are labelled twice: by the
hand-written `data_manifests/kenney_car_kit_rules.toml` and by `labeller.infer` (no rules). The
figure is the area-weighted share of faces given the same part (windows and bumpers compared
before their split into windshield/side/rear and front/rear, which is the same geometry rule for
both). Also printed: the agreement without the floor (faces that look at the ground from the lower
third of the car, which both sides call underbody by the same geometric test), the inferred
up/forward axes against the rules', and the parts confused most. Then, for the five CC-BY models of
../shared/assets/cars3d_cc_by/ (no hand rules exist), the share of each inferred part and what
the proposed rules reproduce.

  python bench/bench_labeller.py [--assets ../shared/assets]
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MERGE = {"windshield": "windows", "window_side": "windows", "window_rear": "windows",
         "bumper_front": "bumpers", "bumper_rear": "bumpers"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--assets", type=Path, default=ROOT.parent / "shared" / "assets")
    ap.add_argument("--goal", type=float, default=0.85)
    a = ap.parse_args()
    import numpy as np

    from blender_gen.cars.faces import read_faces, remove_objects
    from blender_gen.cars.labeller import agreement, infer
    from blender_gen.cars.rules import load_rules, rule_labels

    folder = a.assets / "cars3d"
    models = sorted(folder.glob("*.glb"))
    if not models:
        sys.exit(f"{folder}: no .glb models (the Kenney Car Kit of ../shared/assets)")
    rules = load_rules(ROOT / "data_manifests" / "kenney_car_kit_rules.toml")
    print(f"{'model':10s} {'faces':>6s} {'agree':>6s} {'-floor':>6s}  up/forward (rules)      most confused (hand -> auto, % of area)   s")
    scores = []
    for path in models:
        t0 = time.time()
        table, objects = read_faces([path])
        remove_objects(objects)
        settings = rules.settings_for(path)
        hand, _ = rule_labels(table, rules, settings.default_part, path, settings.up)
        lab = infer(table)
        merge = np.vectorize(lambda p: MERGE.get(p, p), otypes=[object])
        h, auto = merge(hand), merge(lab.labels)
        areas = table.areas()
        score = agreement(h, auto, areas)
        rest = lab.evidence != "geometry"
        no_floor = agreement(h[rest], auto[rest], areas[rest])
        scores.append(score)
        wrong = Counter()
        for x, y, w in zip(h, auto, areas):
            if x != y:
                wrong[f"{x}->{y}"] += w / areas.sum()
        worst = ", ".join(f"{k} {100 * v:.1f}" for k, v in wrong.most_common(3))
        axes = f"{lab.up}/{lab.forward} ({settings.up}/{settings.forward})"
        print(f"{path.stem:10s} {len(table):6d} {100 * score:5.1f}% {100 * no_floor:5.1f}%  {axes:22s}  {worst:42s} {time.time() - t0:.1f}")
    print(f"mean {100 * sum(scores) / len(scores):.1f}%, lowest {100 * min(scores):.1f}%; goal: at least "
          f"{100 * a.goal:.0f}% per model -> {'met' if min(scores) >= a.goal else 'NOT met'}")
    cc_by(a.assets / "cars3d_cc_by")


# The CC-BY models have no hand rules: what the labeller finds is printed (share of the model's
# area per part) with what its proposed rules reproduce, to compare versions by.
CC_BY = {"suv": "gazebo/suv/meshes/suv.obj", "hatchback": "gazebo/hatchback/meshes/hatchback.obj",
         "prius": "gazebo/prius_hybrid/meshes/Hybrid.obj", "ambulance": "gazebo/ambulance/meshes/ambulance.obj",
         "beetle": "metadrive/beetle/vehicle.gltf+metadrive/beetle/right_tire_front.gltf"
                   "+metadrive/beetle/right_tire_back.gltf"}


def cc_by(folder: Path) -> None:
    import tempfile

    from blender_gen.cars.faces import read_car
    from blender_gen.cars.labeller import infer, propose_rules, rules_reproduce

    if not folder.is_dir():
        print(f"{folder}: not found, CC-BY models skipped")
        return
    shown = ("windows", "body", "bumpers", "underbody", "tyres", "rims", "headlights", "tail_lights")
    print("\nCC-BY models (% of area per inferred part; 'rules': proposed rules reproduce the labels)")
    print(f"{'model':10s} {'faces':>6s} " + " ".join(f"{p[:9]:>9s}" for p in shown) + "  rules")
    for name, rel in CC_BY.items():
        files = [folder / p for p in rel.split("+")]
        if not all(f.is_file() for f in files):
            print(f"{name:10s} missing")
            continue
        table, _ = read_car(files)
        lab = infer(table)
        areas = table.areas()
        share = {p: 100 * areas[lab.labels == p].sum() / areas.sum() for p in shown}
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "r.toml"
            path.write_text(propose_rules(table, lab, files[0].name))
            reproduced = rules_reproduce(table, lab, path, files[0])
        print(f"{name:10s} {len(table):6d} " + " ".join(f"{share[p]:9.1f}" for p in shown)
              + f"  {100 * reproduced:.1f}%")


if __name__ == "__main__":
    main()
