# Two commands do all set-up on a fresh machine with Python 3.11:
#   make bench   -> heuristics-vs-policies benchmark on built-in defaults (every registered env),
#                   then the native vector envs' throughput against SyncVectorEnv
#   make test    -> the test suite (what CI runs)
# and, once set up: make docs (the documentation site), make lint, make figures, make perf
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed

# PyTorch build (see docs/getting_started.md): TORCH is the requirement, TORCH_INDEX the wheel
# index tried first (the PyTorch CPU index: the CPU build, ~200 MB). Where that index cannot be
# reached, or with TORCH_INDEX= (empty), pip's configured index serves TORCH; on PyPI a plain
# Linux torch==2.13.0 may be the CUDA build. For CUDA: TORCH_INDEX=<a PyTorch CUDA index>.
TORCH       ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
# pytest workers (pytest-xdist): one per core of the 2-core CI machine
PYTEST_WORKERS ?= 2
PYTEST := $(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadscope

.PHONY: bench test test-detached test-numerics lint docs docs-linkcheck docs-linkcheck-external figures perf perf-vector overheads clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# torch first, so that nothing later resolves another build
	$(PY) -c "import torch" 2>/dev/null || { test -n "$(TORCH_INDEX)" && $(PIP) install --quiet --retries 0 --timeout 20 --index-url "$(TORCH_INDEX)" -c constraints.txt "$(TORCH)"; } || $(PIP) install --quiet -c constraints.txt "$(TORCH)"
	$(PIP) install --quiet -c constraints.txt -e '.[dev,ray,torchrl,clients,docs]'
	$(PY) -c "import torch; print('selenv: torch', torch.__version__, '(CUDA build)' if torch.version.cuda else '(CPU build)')"
	touch $(STAMP)

bench: $(STAMP)
	$(VENV)/bin/selenv bench --episodes 5 --json bench_results.json --plot bench_plots
	$(PY) benchmarks/bench_vector.py --rounds 3 --steps 10

test: $(STAMP)
	$(PYTEST)

# the signal and fault-injection tests launched as `nohup make test &` would launch them: a
# background job of a non-interactive shell, which starts with SIGINT and SIGQUIT ignored (as
# on some CI runners). Not wrapped in `timeout` (that resets the dispositions and hides the
# problem): pytest-timeout is the hang guard. The log is printed; the exit code is pytest's.
# `make test-detached DETACHED_TESTS=tests` runs the whole suite that way (CI launches
# `make test` itself as such a background job: .ci/run).
DETACHED_TESTS ?= tests/test_proc.py tests/test_atomic.py tests/test_bench_faults.py \
	tests/test_ray_faults.py tests/test_ranking_resume.py tests/test_training_faults.py \
	tests/test_rllib.py::test_interrupted_training_keeps_the_last_completed_iteration \
	tests/test_surrogate_faults.py::test_signal_keeps_best_weights_and_resume_equals_an_uninterrupted_run \
	tests/test_surrogate_faults.py::test_external_sigterm_with_periodic_checkpoints
DETACHED_LOG ?= .pytest_cache/test-detached.log

test-detached: $(STAMP)
	@mkdir -p $(dir $(DETACHED_LOG)); rc=0; SELENV_EXPECT_DETACHED=1 bash -c 'nohup $(PYTEST) $(DETACHED_TESTS) > $(DETACHED_LOG) 2>&1 & wait $$!' || rc=$$?; \
	cat $(DETACHED_LOG); echo "test-detached: exit $$rc"; exit $$rc

# the rounding-sensitive tests again under the baseline x86-64 OpenBLAS kernel (another rounding
# than Haswell / SkylakeX): decisions must be identical and values within the stated tolerances
test-numerics: $(STAMP)
	OPENBLAS_CORETYPE=Prescott $(PYTEST) -m numerics

# the documentation site (docs/, Sphinx + furo + MyST) into docs/_build/html, warnings as
# errors; docs-linkcheck checks every internal link and anchor of the built site (no network),
# docs-linkcheck-external the external ones (needs a network; not run by CI)
docs: $(STAMP)
	$(VENV)/bin/sphinx-build -q -W --keep-going -b html docs docs/_build/html
	@echo "docs: open docs/_build/html/index.html"

docs-linkcheck: docs
	$(PY) scripts/check_doc_links.py docs/_build/html

docs-linkcheck-external: $(STAMP)
	$(VENV)/bin/sphinx-build -q -b linkcheck docs docs/_build/linkcheck

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check . && $(VENV)/bin/mypy

figures: $(STAMP)
	$(PY) scripts/reproduce_kirchner.py && $(PY) scripts/reproduce_greiff.py && $(PY) scripts/reproduce_soubaras.py && $(PY) scripts/reproduce_chen_kia.py && $(PY) scripts/reproduce_chen_kia_surrogates.py

perf: $(STAMP)
	$(PY) benchmarks/bench_greedy.py && $(PY) benchmarks/bench_env_step.py && $(PY) benchmarks/bench_clustering.py && $(PY) benchmarks/bench_landmarks.py && $(PY) benchmarks/bench_fusion.py && $(PY) benchmarks/bench_surrogates.py

# native vector envs vs SyncVectorEnv and CartPole-v1, scaling in B and in each family's size
# (docs/performance/vector_envs.md); bench_threads: the solvers with the default thread counts
perf-vector: $(STAMP)
	$(PY) benchmarks/bench_vector.py --scaling --json docs/bench/vector_envs.json && $(PY) benchmarks/bench_threads.py

# the overhead ratios (docs/performance/overheads.md);
# bench_kalman.py compares with FilterPy if it is installed (pip install filterpy==1.4.5)
overheads: $(STAMP)
	export OPENBLAS_NUM_THREADS=1; $(PY) benchmarks/bench_greedy_setup.py && $(PY) benchmarks/bench_clustering.py --compare --rounds 300 && $(PY) benchmarks/bench_clustering.py --env-step --rounds 100 && $(PY) benchmarks/bench_env_step.py --target overheads --rounds 15 && $(PY) benchmarks/bench_fusion.py --scaling --rounds 31 && $(PY) benchmarks/bench_kalman.py --rounds 41

clean:
	rm -rf $(VENV) bench_results.json bench_plots docs/_build .pytest_cache .ruff_cache .mypy_cache
