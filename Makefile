# Two commands do all set-up on a fresh machine with Python 3.11:
#   make bench   -> heuristics-vs-policies benchmark on built-in defaults (every registered env)
#   make test    -> the test suite (what CI runs)
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed

.PHONY: bench test lint figures perf overheads clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# torch first, pinned to the CPU wheel, so nothing later resolves the CUDA build
	$(PIP) install --quiet -c constraints.txt torch==2.13.0
	$(PIP) install --quiet -c constraints.txt -e '.[dev,ray]'
	touch $(STAMP)

bench: $(STAMP)
	$(VENV)/bin/selenv bench --episodes 5 --json bench_results.json --plot bench_plots

test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check . && $(VENV)/bin/mypy

figures: $(STAMP)
	$(PY) scripts/reproduce_kirchner.py && $(PY) scripts/reproduce_greiff.py && $(PY) scripts/reproduce_soubaras.py && $(PY) scripts/reproduce_chen_kia.py && $(PY) scripts/reproduce_chen_kia_surrogates.py

perf: $(STAMP)
	$(PY) benchmarks/bench_greedy.py && $(PY) benchmarks/bench_env_step.py && $(PY) benchmarks/bench_clustering.py && $(PY) benchmarks/bench_landmarks.py && $(PY) benchmarks/bench_fusion.py && $(PY) benchmarks/bench_surrogates.py

# the issue-19 overhead ratios (docs/BENCHMARKS.md, "Overheads around the core algorithms");
# bench_kalman.py compares with FilterPy if it is installed (pip install filterpy==1.4.5)
overheads: $(STAMP)
	export OPENBLAS_NUM_THREADS=1; $(PY) benchmarks/bench_greedy_setup.py && $(PY) benchmarks/bench_clustering.py --compare --rounds 300 && $(PY) benchmarks/bench_clustering.py --env-step --rounds 100 && $(PY) benchmarks/bench_env_step.py --target issue19 --rounds 15 && $(PY) benchmarks/bench_fusion.py --scaling --rounds 31 && $(PY) benchmarks/bench_kalman.py --rounds 41

clean:
	rm -rf $(VENV) bench_results.json bench_plots .pytest_cache .ruff_cache .mypy_cache
