PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv demo test docs bench clean

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

clean:
	rm -rf $(VENV) out build *.egg-info
