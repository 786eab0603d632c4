# piezo_stage: the README's commands. Each target sets up first (quick when already set up).
SHELL := /bin/bash
ENV := source scripts/env.sh &&

.PHONY: setup demo test test-fast fuzz lint bench clean
setup:            ## .venv + pinned wheels, wheel fixes, piezo_stage_msgs build (idempotent)
	@bash scripts/setup.sh
demo: setup       ## the simulated stage, end to end
	@$(ENV) piezo-stage demo --out demo_out
PYTEST := python -m pytest test -q -p no:cacheprovider --durations=50
test: setup lint  ## lint, then every test: all but `realtime`/`alone` on two workers, then those alone
	@$(ENV) $(PYTEST) -n 2 --dist loadfile --no-loadscope-reorder -m "not realtime and not alone" && $(PYTEST) -m "realtime or alone"
test-fast: setup  ## the unit layer without slow tests (no ROS processes, no sockets; < 1 min)
	@$(ENV) $(PYTEST) -n 2 -m "unit and not slow"
fuzz: setup       ## property tests with random seeds, FUZZ x their examples (default 50)
	@$(ENV) PIEZO_FUZZ_FACTOR=$${FUZZ:-50} $(PYTEST) -m hypothesis \
	  --hypothesis-profile=fuzz --hypothesis-show-statistics
lint: setup       ## ruff (D on the core), ruff format, mypy strict, import layers, complexity <= 20
	@$(ENV) ruff check . && ruff format --check . && mypy \
	  && { out=$$(lint-imports --no-cache 2>&1) || { echo "$$out"; exit 1; }; \
	       echo "$$out" | tail -n 1; } \
	  && python scripts/check_complexity.py
bench: setup      ## speed/accuracy figures against their baselines
	@$(ENV) for b in bench/*.py; do echo "== $$b"; python $$b || exit 1; done
clean:
	rm -rf build install log .venv
