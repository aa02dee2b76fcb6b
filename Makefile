# Developer and CI entry points. Every target but clean and distclean first runs
# scripts/bootstrap.sh, which creates .venv (ROS 2 Jazzy Python wheels + dev tools + this
# package, editable) and is a no-op when nothing changed.
#   make test PYTEST_ARGS='-k solver -x'     extra pytest arguments
#   make demo DEMO_ARGS='...'                extra arguments of the demo tool
SHELL := /bin/bash
PY := .venv/bin/python
PYTEST_ARGS ?=
DEMO_ARGS ?=
# Nodes started here talk over real DDS: keep discovery on this machine.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: bootstrap demo test bench clean distclean

bootstrap:
	bash scripts/bootstrap.sh

demo: bootstrap
	$(PY) -m quatcal_ros demo $(DEMO_ARGS)

# Ends with pytest's own summary line (.ci/run reads it). No bytecode in the tree from the
# modules pytest imports before test/conftest.py moves the caches to the session directory.
test: bootstrap
	PYTHONDONTWRITEBYTECODE=1 $(PY) -m pytest -p no:cacheprovider $(PYTEST_ARGS) test

# Each benchmark is a bench/bench_*.py script that prints a table; they run one after the
# other (bench/'s other scripts are their helpers, such as opencv_solve_csv.py).
bench: bootstrap
	@set -e; shopt -s nullglob; scripts=(bench/bench_*.py); \
	if [ $${#scripts[@]} -eq 0 ]; then echo 'bench: no bench/bench_*.py scripts'; fi; \
	for s in "$${scripts[@]}"; do echo "== $$s"; $(PY) "$$s"; done

# Build outputs and caches; distclean also removes .venv.
clean:
	rm -rf build install log .pytest_cache .hypothesis *.egg-info
	find . -path ./.venv -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf .venv
