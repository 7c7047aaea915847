# formtwin: `make demo` runs the main job, `make test` the tests (lint, the docs site, pytest).
# Both build .venv themselves; `make docs` builds the documentation site alone.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# the part of the venv the Numba kernels need (core, physics, data), installed first
CORE := $(VENV)/.core
# pytest workers (pytest-xdist): the 2 cores CI has (the tests keep both cores busy while
# they wait on the services and commands they start: 3 workers took 577 s against 497-537)
TEST_WORKERS ?= 2

.PHONY: demo test lint kernels docs bench live-demo system-deps fe-deps apt-deps clean

# the venv: pip installs uv (one download), uv installs the packages (its resolver, parallel
# downloads and its own cache; measured on a 2-core machine: 25 s where pip took 120 s for
# the same versions), the core first (what the Numba kernels need), then the rest. Neither
# byte-compiles every installed module: modules are compiled when first imported, not all at
# once. That needs bytecode writing on: with PYTHONDONTWRITEBYTECODE set (some CI images set
# it) every process the tests start (services, commands, pool workers) would compile numpy,
# scipy, matplotlib and numba from source again, ~8 s of CPU each; the recipes run without it
unexport PYTHONDONTWRITEBYTECODE
# uv reads neither pip.conf nor PIP_* variables: the package sources pip is configured with
# (mirror index, wheel folders, constraints, certificate) are given to it as flags
UV = $(BIN)/uv pip install --quiet --python $(BIN)/python $$($(BIN)/python scripts/uv_sources.py)
$(CORE): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check uv
	$(UV) -e '.[physics,data]'
	touch $(CORE)

$(STAMP): $(CORE)
	$(UV) -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/formtwin demo

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks examples scripts docs/conf.py docs/_ext docs/figures
	@# the product's words: no work periods, locks, who ran what, clock times or machine paths
	$(BIN)/python scripts/check_words.py
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(BIN)/interrogate -c pyproject.toml src/formtwin
	@# small modules with one job: none in src over 400 lines
	@find src -name '*.py' | xargs wc -l | \
	    awk '$$2 != "total" && $$1 > 400 {print "over 400 lines: " $$2 " (" $$1 ")"; bad = 1} \
	    END {exit bad}'

# the documentation site (Sphinx + MyST): warnings are errors, so a broken link, anchor or
# reference fails; docs/_build/html/index.html is the site
docs: $(STAMP)
	$(BIN)/sphinx-build -b html -W --keep-going -q -d docs/_build/doctrees docs docs/_build/html

# the venv's core, then the compile of the Numba kernels into their cache (from the sources,
# scripts/compile_kernels.py: the workers load them instead of each compiling them; ~50 s on
# one core) beside the rest of the venv, the Debian packages (apt) and then the lint and the
# docs site, niced (the kernels are what pytest waits on; the lint and the docs site take
# the other core, and what is left of them the CPU the workers leave while they wait on the
# services and commands they start; their logs shown if they fail). Then pytest on both
# cores: the workers take one test (or group, tests/conftest.py) at a time, the longest
# first, so that they end together; the 25 slowest are listed.
test: $(CORE)
	@mkdir -p docs/_build build
	@echo "kernels, lint and docs site: beside the install and pytest" \
	    "(build/kernels.log, build/lint.log, docs/_build/sphinx.log)"
	@$(MAKE) --no-print-directory kernels > build/kernels.log 2>&1 & kernels=$$!; \
	$(MAKE) --no-print-directory -j2 $(STAMP) apt-deps || { wait $$kernels; exit 1; }; \
	nice $(MAKE) --no-print-directory lint > build/lint.log 2>&1 & lint=$$!; \
	nice $(BIN)/sphinx-build -b html -W --keep-going -q -d docs/_build/doctrees docs \
	    docs/_build/html > docs/_build/sphinx.log 2>&1 & docs=$$!; \
	if wait $$kernels; then cat build/kernels.log; \
	else cat build/kernels.log; echo "kernels: FAILED"; wait $$lint $$docs; exit 1; fi; \
	OMP_NUM_THREADS=1 $(BIN)/pytest -n $(TEST_WORKERS) --dist loadgroup --durations=25; \
	rc=$$?; \
	if wait $$lint; then echo "lint: passed"; \
	else cat build/lint.log; echo "lint: FAILED"; rc=1; fi; \
	if wait $$docs; then echo "docs site: built"; \
	else cat docs/_build/sphinx.log; echo "docs site: FAILED"; rc=1; fi; exit $$rc

# the Numba kernels compiled into their on-disk cache (each kernel once, not once per process);
# from the sources (PYTHONPATH), so that it can run while pip installs the rest of the venv
kernels: $(CORE)
	OMP_NUM_THREADS=1 PYTHONPATH=src $(BIN)/python scripts/compile_kernels.py

# every missing Debian package of system-deps and fe-deps in one apt-get run
apt-deps:
	@need=""; \
	{ command -v mosquitto || test -x /usr/sbin/mosquitto; } >/dev/null || need="$$need mosquitto"; \
	command -v chromium >/dev/null || need="$$need chromium"; \
	command -v openssl >/dev/null || need="$$need openssl"; \
	command -v ccx >/dev/null || need="$$need calculix-ccx"; \
	if [ -z "$$need" ]; then :; \
	elif [ "$$(id -u)" = 0 ]; then \
	    echo "apt-get install$$need"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	        apt-get install -y -qq -o DPkg::Lock::Timeout=300 $$need; \
	else echo "apt-deps:$$need missing and not root: their tests will skip"; fi

# the service tests need a real mosquitto broker and a headless chromium (Debian packages)
system-deps:
	@if { command -v mosquitto || test -x /usr/sbin/mosquitto; } >/dev/null && \
	    command -v chromium >/dev/null && command -v openssl >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	        apt-get install -y -qq mosquitto chromium openssl; \
	else echo "system-deps: mosquitto/chromium missing and not root: service tests will skip"; fi

# the CalculiX model and its tests need ccx (Debian package calculix-ccx, 2.20 on bookworm)
fe-deps:
	@if command -v ccx >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ]; then \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	        apt-get install -y -qq -o DPkg::Lock::Timeout=300 calculix-ccx; \
	else echo "fe-deps: ccx missing and not root: CalculiX tests will skip"; fi

# closed-loop control of the final angle (physics model as the plant; heavy: ~15000 physics
# runs): fixed u, run-to-run EWMA, feedforward from the estimates, oracle
control-study: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/formtwin control-study --out benchmarks/.cache/control

live-demo: $(STAMP) system-deps
	OMP_NUM_THREADS=1 $(BIN)/python -m formtwin.service.livedemo

bench: $(STAMP)
	for f in benchmarks/bench_*.py; do $(BIN)/python $$f || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info docs/_build
