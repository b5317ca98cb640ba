PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv demo test docs bench gpu-check clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

demo: venv
	$(PY) -m gcp_stereo_ros.tools.demo --out out

test: venv
	$(PY) -m pytest -q test

# The manual (doc/, Sphinx + MyST) as HTML in build/docs; any warning fails the build.
docs: venv
	$(PY) -m sphinx -W --keep-going -b html doc build/docs

bench: venv
	$(PY) -m gcp_stereo_ros.tools.bench

# On a GPU machine, with its own python3 (a CUDA build of torch, numba-cuda; no venv), in at
# most 5 minutes: the CUDA kernels and whole frames against the CPU, then the GPU bench on
# KITTI 000070 (medians of 15 pairs). JSON and a junit report into GPU_OUT.
GPU_DATA ?= ../shared/data
GPU_OUT ?= build/gpu
gpu-check:
	mkdir -p $(GPU_OUT)
	GCP_STEREO_DATA=$(GPU_DATA) NUMBA_ENABLE_CUDASIM=0 $(PYTHON) -m pytest -q -p no:cacheprovider \
		test/cuda_checks.py --junitxml=$(GPU_OUT)/cuda_checks.xml
	$(PYTHON) -m gcp_stereo_ros.tools.bench --device cuda --repeat 15 --dataset $(GPU_DATA) \
		--frame kitti2012/000070_10 --json $(GPU_OUT)/bench.json

clean:
	rm -rf $(VENV) out build *.egg-info
