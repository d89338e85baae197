#!/usr/bin/env bash
# Hostile inputs, rerun by hand through the command lines (not part of `make test`, whose
# tests cover each case one by one): every case prints PASS or FAIL and a summary closes the run.
# Usage (from a checkout with its virtual environment made by `make`):  bash .ci/hostile.sh [WORKDIR]
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
W=${1:-$(mktemp -d /tmp/hostile.XXXX)}
mkdir -p "$W"
export PATH="$ROOT/.venv/bin:$PATH" OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
PY="$ROOT/.venv/bin/python"
cd "$ROOT"
pass=0; fail=0
TINY=(--set data.height=32 --set data.width=64 --set data.batch_size=2 --set data.workers=0 --set model.r_ngf=8
      --set model.r_downsample=2 --set model.r_blocks=1 --set model.h_ngf=8 --set model.h_blocks=1 --set model.d_ndf=8
      --set run.probe_every=0 --set run.grid_every=1000)

# case NAME EXPECTED_RC_REGEX TEXT_REGEX -- COMMAND...: the exit status and the output (stdout+stderr)
case_() {
  local name=$1 rc_re=$2 text_re=$3; shift 4
  local out rc
  out=$("$@" 2>&1); rc=$?
  if [[ $rc =~ ^($rc_re)$ ]] && grep -Eq -- "$text_re" <<<"$out" && ! grep -q Traceback <<<"$out"; then
    echo "PASS  $name"; pass=$((pass + 1))
  else
    echo "FAIL  $name (exit $rc)"; tail -3 <<<"$out" | sed 's/^/      /'; fail=$((fail + 1))
  fi
}
check() {  # check NAME COMMAND...: passes when the command (a test of files) succeeds
  local name=$1; shift
  if "$@"; then echo "PASS  $name"; pass=$((pass + 1)); else echo "FAIL  $name"; fail=$((fail + 1)); fi
}

echo "== data ($W)"
iae-gen intrinsics --out "$W/intr" --count 8 --resolution 64x32 --seed 3 --quiet
iae-gen pbr --out "$W/pbr" --count 8 --resolution 64x32 --samples 2 --seed 3 --quiet
iae-gen pbr --out "$W/pbr_eval" --count 4 --resolution 64x32 --samples 2 --seed 4 --quiet
iae-gen intrinsics --out "$W/intr_fid" --count 4 --resolution 64x32 --seed 5 --quiet

echo "== 1 stale report figures"
iae-train fit --config cpu-small --intrinsics "$W/intr" --real "$W/pbr" --run-dir "$W/run" --max-steps 2 --quiet "${TINY[@]}" >/dev/null
report() { iae-eval report "$W/run" --data "$W/pbr_eval" --real "$W/pbr" --intrinsics "$W/intr_fid" --out "$W/rep" --quiet >/dev/null; }
report
first=$(grep "^| run | " "$W/rep/report.md" | sed -n 2p | cut -d"|" -f4-9)
rm -rf "$W/run"
iae-train fit --config cpu-small --intrinsics "$W/intr" --real "$W/pbr" --run-dir "$W/run" --max-steps 2 --quiet "${TINY[@]}" --set run.seed=9 >/dev/null
report
second=$(grep "^| run | " "$W/rep/report.md" | sed -n 2p | cut -d"|" -f4-9)
echo "      Table 3 before: $first"; echo "      Table 3 after:  $second"
check "1 retrained in place (other seed, same step): new Table-3 figures" test -n "$first" -a "$first" != "$second"

echo "== 2 a resumed sample is the sample (intrinsics and PBR, samples 1 and 2 of a block)"
for kind in intr pbr; do
  for i in 000001 000002; do
    before=$(sha256sum "$W/$kind/samples/$i.exr" | cut -c1-64); rm "$W/$kind/samples/$i.exr"
    if [ $kind = intr ]; then iae-gen intrinsics --out "$W/intr" --count 8 --resolution 64x32 --seed 3 --quiet
    else iae-gen pbr --out "$W/pbr" --count 8 --resolution 64x32 --samples 2 --seed 3 --quiet; fi
    check "2 $kind sample $i re-rendered byte-identical" test "$before" = "$(sha256sum "$W/$kind/samples/$i.exr" | cut -c1-64)"
  done
done

echo "== 3 one writer per run folder"
# the first fit runs long enough to still hold the lock; it is taken before the options are written
iae-train fit --config cpu-small --intrinsics "$W/intr" --real "$W/pbr" --run-dir "$W/two" --max-steps 100000 --quiet "${TINY[@]}" >/dev/null 2>&1 &
first=$!
for _ in $(seq 120); do [ -f "$W/two/training_options.json" ] && break; sleep 0.5; done
case_ "3 a second fit in the same run folder is refused" 1 "in use|another|lock" -- \
  iae-train fit --run-dir "$W/two" --quiet
kill -TERM $first; wait $first
case_ "3 --runs full,,full refused" "1|2" "twice|empty|Invalid value for --runs" -- iae-eval reproduce --budget smoke --runs full,,full --out "$W/rr" --dry-run

echo "== 4 export never overwrites"
ck=$(ls "$W/run/checkpoints/"*.safetensors | tail -1)
case_ "4 export --out an existing checkpoint refused" "1|2" "exists|inside|run folder" -- \
  iae-train export --run "$W/run" --net R --out "$ck"
case_ "4 export into a run folder refused" "1|2" "run folder|inside" -- \
  iae-train export --run "$W/run" --net R --out "$W/run/R.onnx"
touch "$W/v.mp4"
case_ "4 render --video over an existing file refused" "1|2" "exists" -- \
  iae-train render --run "$W/run" --intrinsics "$W/intr" --out "$W/frames" --video "$W/v.mp4" --quiet

echo "== 5 a refused turntable leaves nothing"
case_ "5 turntable --radius 0.5 refused" "1|2" "radius" -- \
  iae-gen turntable --out "$W/tt" --car sedan_a --frames 3 --resolution 64x32 --radius 0.5 --quiet
check "5 ... and wrote no dataset.json" test ! -e "$W/tt/dataset.json"
case_ "5 turntable --radius nan refused" "1|2" "radius" -- \
  iae-gen turntable --out "$W/tt" --car sedan_a --frames 3 --resolution 64x32 --radius nan --quiet
case_ "5 the corrected command then works" 0 "" -- \
  iae-gen turntable --out "$W/tt" --car sedan_a --frames 3 --resolution 64x32 --radius 7 --quiet

echo "== 6 16-bit grey photos"
"$PY" - "$W/grey" <<'EOF'
import sys, numpy as np
from pathlib import Path
from PIL import Image
d = Path(sys.argv[1]); d.mkdir(exist_ok=True)
Image.fromarray((np.linspace(0, 65535, 64 * 32).reshape(32, 64)).astype(np.uint16)).save(d / "g16.png")
EOF
"$PY" - "$W/grey/g16.png" > "$W/grey.txt" <<'EOF'
import sys
from PIL import Image
from train.data import photo_to_srgb01
a = photo_to_srgb01(Image.open(sys.argv[1]))
print(f"saturated {(a >= 0.999).mean():.3f} mean {a.mean():.3f}")
EOF
check "6 a 16-bit grey PNG loads as its grey ramp, not white ($(cat "$W/grey.txt"))" \
  "$PY" -c "import sys; t=open('$W/grey.txt').read().split(); sys.exit(not (float(t[1]) < 0.05 and 0.4 < float(t[3]) < 0.6))"

echo "== 7/8 the A/B study"
mkdir -p "$W/a" "$W/b"
for i in 0 1 2; do cp "$W/pbr/previews/00000$i.png" "$W/a/$i.png"; cp "$W/pbr/previews/00000$i.png" "$W/b/$i.png"; done
case_ "8 a label with <!--<script> gives a working page" 0 "" -- \
  iae-eval ab-study --a "$W/a" --b "$W/b" --pairs 3 --out "$W/study" --label-b '<!--<script>'
check "8 ... the raw label appears nowhere in the page" sh -c "! grep -q '<!--<script>' '$W/study/'*.html"
case_ "8 --pairs beyond the distinct scenes is refused or capped" "0|1|2" "distinct|cap|only" -- \
  iae-eval ab-study --a "$W/a" --b "$W/b" --pairs 500 --out "$W/study2"
"$PY" - "$W/study" > "$W/answers.json" <<'EOF'
import json, sys
from pathlib import Path
key = json.loads((Path(sys.argv[1]) / "study.json").read_text())
print(json.dumps({"schema": key["schema"], "study": key["study"], "participant": "p1",
                  "answers": [{"pair": p["pair"], "kind": p["kind"], "chosen": p["left"]} for p in key["pairs"]]}))
EOF
case_ "7 one answer file counts once" 0 "" -- iae-eval ab-summary --study "$W/study/study.json" "$W/answers.json"
case_ "7 the same answer file twice is refused" "1|2" "same answers|once" -- \
  iae-eval ab-summary --study "$W/study/study.json" "$W/answers.json" "$W/answers.json"
"$PY" - "$W/answers.json" > "$W/answers_extra.json" <<'EOF'
import json, sys
a = json.load(open(sys.argv[1])); a["participant"] = "p2"
a["answers"].append({**a["answers"][0], "pair": 9999}); print(json.dumps(a))
EOF
case_ "7 answers for a pair the study does not have are refused" "1|2" "not in this study" -- \
  iae-eval ab-summary --study "$W/study/study.json" "$W/answers_extra.json"

echo "== 9 one Ctrl-C stops a Cycles render with 130"
set -m  # job control: a background job that ignores SIGINT would not be what a terminal's Ctrl-C meets
# the Ctrl-C a terminal sends reaches a program whose SIGINT is not ignored: a script started in the
# background (nohup ... &) inherits an ignored SIGINT, so restore the default before the command
"$PY" -c 'import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execvp(sys.argv[1], sys.argv[1:])' \
  iae-gen turntable --out "$W/ttp" --car sedan_a --frames 60 --resolution 128x64 --radius 7 --pbr --samples 64 --quiet >"$W/ctrlc.txt" 2>&1 &
pid=$!; sleep 12; kill -INT $pid; wait $pid; rc=$?
set +m
check "9 exit status $rc after one SIGINT, no traceback" sh -c "[ $rc = 130 ] && ! grep -q Traceback '$W/ctrlc.txt'"

echo "== 10 one-line errors"
case_ "10 export --resolution 100000x100000" "1|2" "resolution" -- \
  iae-train export --run "$W/run" --net R --out "$W/big.onnx" --resolution 100000x100000
iae-train export --run "$W/run" --net R --out "$W/R.onnx" >/dev/null 2>&1
"$PY" - "$W/R.onnx" <<'EOF'
import sys, onnx
m = onnx.load(sys.argv[1])
for p in m.metadata_props:
    if p.key == "height":
        p.value = '"tall"'
onnx.save(m, sys.argv[1])
EOF
case_ "10 check-export on edited metadata" "1|2" "height|metadata|expected" -- \
  iae-train check-export --run "$W/run" "$W/R.onnx"
"$PY" -c "from PIL import Image; Image.new('L', (30000, 30000)).save('$W/bomb.png')"
case_ "10 decompress-bomb PNG in decompose" "1|2" "pixels|large|bomb" -- \
  iae-train decompose --run "$W/run" --images "$W/bomb.png" --out "$W/dec"
check "10 ... and no half-written --out" test ! -e "$W/dec/bomb.png"
mkdir -p "$W/shots" && "$PY" -c "from PIL import Image; Image.new('RGB', (300, 200), (90, 60, 30)).save('$W/shots/my_car.jpg')"
printf 'not a jpeg' > "$W/shots/broken.jpg"
case_ "10 decompose --size 0" "1|2" "--size '0': expected photo, a longer side" -- \
  iae-train decompose --run "$W/run" --images "$W/shots" --out "$W/dec_s" --size 0
case_ "10 a broken photo is skipped, named, exit 0" 0 "skipped: .*broken.jpg" -- \
  iae-train decompose --run "$W/run" --images "$W/shots" --out "$W/dec_b" --quiet
case_ "10 ... and exit 1 with --strict" 1 "broken.jpg" -- \
  iae-train decompose --run "$W/run" --images "$W/shots" --out "$W/dec_c" --quiet --strict
check "10 ... my_car's maps at 300x200, EXR beside" "$PY" -c "
from PIL import Image; import sys
sys.exit(Image.open('$W/dec_b/photos/my_car_albedo.png').size != (300, 200) or not __import__('os').path.exists('$W/dec_b/photos/my_car.exr'))"
case_ "10 flicker on a PBR set that is not a camera path" 1 "not a camera path" -- \
  iae-eval flicker --run "$W/run" --path "$W/pbr"

echo "== 11 video options"
case_ "11 render --video --fps nan" "1|2" "fps" -- \
  iae-train render --run "$W/run" --intrinsics "$W/intr" --out "$W/f2" --video "$W/v2.mp4" --fps nan
case_ "11 a video in a read-only folder: one line naming why, before any frame" 1 "cannot write in /sys: Permission denied" -- \
  iae-train render --run "$W/run" --intrinsics "$W/intr" --out "$W/f5" --video /sys/iae.mp4

echo "== 12 planning and progress"
case_ "12 reproduce --dry-run --jobs 100 caps the jobs" 0 "job" -- iae-eval reproduce --budget cpu --dry-run --jobs 100 --out "$W/r2"
case_ "12 --resolution 50x30 (width x height) refused before any data" "1|2" "multiples of" -- \
  iae-eval reproduce --budget smoke --resolution 50x30 --out "$W/r3"
check "12 ... and nothing generated" test ! -e "$W/r3/data"

echo "== 13 no CUDA probe warning"
case_ "13 iae-gen pbr prints no CUEW line" 0 "samples" -- sh -c "iae-gen pbr --out '$W/p13' --count 1 --resolution 64x32 --samples 1 2>&1 | grep -v CUEW; iae-gen pbr --out '$W/p13b' --count 1 --resolution 64x32 --samples 1 2>&1 | grep -c CUEW | grep -qx 0 && echo 'samples ok'"

echo "== 14 damaged data"
cp -r "$W/intr" "$W/bad"
cp "$W/bad/samples/000000.exr" "$W/bad/samples/000001.exr"
case_ "14 a sample copied over another is caught by render" "1|2" "000001|checksum" -- \
  iae-train render --run "$W/run" --intrinsics "$W/bad" --out "$W/f3"

echo "== third pass: one checkpoint, one set, no output over an input"
cp "$W/run/checkpoints/$(ls "$W/run/checkpoints" | grep safetensors | tail -1)" "$W/ckpt_backup"
case_ "5 diagnose --json over the newest checkpoint" 1 "inside the run folder" -- \
  iae-train diagnose --run "$W/run" --probe "$W/pbr_eval" --json "$W/run/checkpoints/$(ls "$W/run/checkpoints" | grep safetensors | tail -1)" --force
check "5 ... and the checkpoint is intact" cmp -s "$W/ckpt_backup" "$W/run/checkpoints/$(ls "$W/run/checkpoints" | grep safetensors | tail -1)"
case_ "5 flicker --out over a dataset's dataset.json" 1 "inside the dataset folder" -- \
  iae-eval flicker --run "$W/run" --path "$W/pbr" --out "$W/pbr/dataset.json"
echo '{"runs": []}' > "$W/results_mine.json"
case_ "5 seeds --out over an existing file" 1 "exists; choose a new file or pass --force" -- \
  iae-eval seeds "$W/results_mine.json" --out "$W/results_mine.json"
case_ "13 diagnose --checkpoint of another run" 1 "not a checkpoint of --run" -- \
  iae-train diagnose --run "$W/run" --probe "$W/pbr_eval" --checkpoint "$W/ckpt_backup"
cp -r "$W/intr" "$W/intr_short"
"$PY" - "$W/intr_short/dataset.json" <<'PYEOF'
import json, sys
p = sys.argv[1]; d = json.load(open(p)); d["count_requested"] = d["count"] + 4; d["complete"] = False
json.dump(d, open(p, "w"))
PYEOF
case_ "6 fit on an incomplete set" 1 "incomplete \(8 of 12 samples\)" -- \
  iae-train fit --config cpu-small --intrinsics "$W/intr_short" --real "$W/pbr" --run-dir "$W/run6" --max-steps 1 --quiet "${TINY[@]}"
check "6 ... and no run folder" test ! -e "$W/run6"
cp -r "$W/intr" "$W/intr_grow"
iae-train fit --config cpu-small --intrinsics "$W/intr_grow" --real "$W/pbr" --run-dir "$W/run6b" --max-steps 1 --quiet "${TINY[@]}" >/dev/null
iae-gen intrinsics --out "$W/intr_grow" --count 12 --resolution 64x32 --seed 3 --quiet >/dev/null
case_ "6 a resume after the set grew from 8 to 12" 1 "changed since .*8 -> 12 samples" -- \
  iae-train fit --run-dir "$W/run6b" --max-steps 2 --quiet
case_ "6 ... accepted explicitly, and recorded" 0 "step 2" -- \
  iae-train fit --run-dir "$W/run6b" --max-steps 2 --quiet --accept-changed-data
check "6 ... the change is in the run's options" grep -q data_changes "$W/run6b/training_options.json"
mkdir -p "$W/objcar"
printf 'newmtl body\nKd 0.8 0.1 0.1\n' > "$W/objcar/car.mtl"
printf 'mtllib car.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl body\nf 1 2 3\n' > "$W/objcar/car.obj"
case_ "1 a recipe names the .mtl its OBJ reads" 0 "car.mtl" -- \
  "$PY" -c "from blender_gen.recipe import Recipe; print(Recipe(kind='intrinsics', seed=0, width=64, height=32, cars=('$W/objcar/car.obj',)).identity()['cars'])"

echo "== summary: $pass passed, $fail failed"
[ "$fail" = 0 ]
