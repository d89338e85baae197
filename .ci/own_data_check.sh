#!/usr/bin/env bash
# The own-data journey at toy size, as a user runs it: a folder of car models (the Kenney Car Kit
# beside the repository) with inferred parts, and a folder of JPG "photos" of mixed sizes
# (close-framed PBR renders of held-out cars stand in for photos). The plan must estimate the
# photos' framing, and the report must show the photo gallery.
set -euo pipefail
cd "$(dirname "$0")/.."
CARS=../shared/assets/cars3d
if [ ! -d "$CARS" ]; then
    echo "own-data check: $CARS is missing"; exit 1
fi
OUT=out/ci_own_data
rm -rf "$OUT"
.venv/bin/iae-gen pbr --out "$OUT/photos_pbr" --count 12 --seed 5 --resolution 256x128 --samples 2 \
    --cars procedural:heldout --envmap procedural:heldout --min-coverage 0.45 --max-coverage 0.75 --quiet
.venv/bin/python - "$OUT" <<'PY'
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from blender_gen.conversions import linear_to_srgb
from blender_gen.dataset import open_dataset

out = Path(sys.argv[1])
ds = open_dataset(out / "photos_pbr")
photos = out / "photos"
photos.mkdir()
for i in range(len(ds)):  # JPEGs of mixed sizes and aspect ratios, as photos come
    rgb = (linear_to_srgb(ds.load(i, ["rgb"])["rgb"][..., :3]) * 255 + 0.5).astype(np.uint8)
    size = [(256, 128), (400, 200), (300, 200), (640, 320)][i % 4]
    Image.fromarray(rgb).resize(size, Image.BICUBIC).save(photos / f"my_car_{i:02d}.jpg", quality=90)
PY
.venv/bin/iae-eval reproduce --budget smoke --cars "$CARS" --car-rules auto --real "$OUT/photos" --runs full \
    --out "$OUT/run" | tee "$OUT/reproduce.log"
grep -q "framing   your photos: the car fills" "$OUT/reproduce.log"
grep -q "Your photos: each run's decomposition" "$OUT/run/report/report.html"
ls "$OUT"/run/report/runs/*/gallery/photos/my_car_*.png > /dev/null
echo "own-data check: passed"
