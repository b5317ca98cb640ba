PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv demo test docs bench gpu-check gpu-bundle clean

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
# KITTI 000070 (medians of 15 pairs). JSON and a junit report into GPU_OUT. gpu-bundle, here,
# puts what that machine lacks into .gpu/ (git-ignored): the frames, and numpy below 2.5 for
# its Python 3.12 (numba-cuda needs it). The device tool's run, carrying .gpu:
#   PYTHONPATH=.gpu/site make gpu-check PYTHON=python3 GPU_DATA=.gpu/data GPU_OUT=$OUT
GPU_DATA ?= ../shared/data
GPU_OUT ?= build/gpu
GPU_FRAMES := kitti2012/training/*/000070_10.* kitti2012/training/calib/000070.txt \
	kitti2015/training/*/00003[1-9]_10.png kitti2015/training/*/000040_10.png
gpu-check:
	if [ -d .gpu/wheels ]; then $(PYTHON) -m pip install -q --no-deps --target .gpu/site .gpu/wheels/*.whl; fi
	mkdir -p $(GPU_OUT)
	status=0; GCP_STEREO_DATA=$(GPU_DATA) NUMBA_ENABLE_CUDASIM=0 $(PYTHON) -m pytest -q \
		-p no:cacheprovider test/cuda_checks.py test/cuda_invalidate_checks.py --junitxml=$(GPU_OUT)/cuda_checks.xml || status=$$?; \
	$(PYTHON) -m gcp_stereo_ros.tools.bench --device cuda --repeat 15 --dataset $(GPU_DATA) \
		--frame kitti2012/000070_10 --json $(GPU_OUT)/bench.json || status=$$?; exit $$status

gpu-bundle: venv
	rm -rf .gpu && mkdir -p .gpu/data
	cd ../shared/data && cp --parents $(GPU_FRAMES) $(CURDIR)/.gpu/data/
	$(PY) -m pip download -q numpy==2.4.6 --python-version 3.12 --only-binary=:all: --no-deps \
		--platform manylinux_2_28_x86_64 -d .gpu/wheels

clean:
	rm -rf $(VENV) out build *.egg-info
