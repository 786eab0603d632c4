# piezo_stage: the README's commands. Each target sets up first (quick when already set up).
SHELL := /bin/bash
ENV := source scripts/env.sh &&

.PHONY: setup demo test bench clean
setup:            ## .venv + pinned wheels, wheel fixes, piezo_stage_msgs build (idempotent)
	@bash scripts/setup.sh
demo: setup       ## the simulated stage, end to end
	@$(ENV) piezo-stage demo --out demo_out
test: setup       ## every test (pytest over test/)
	@$(ENV) python -m pytest test -q -p no:cacheprovider
bench: setup      ## speed/accuracy figures against their baselines
	@$(ENV) for b in bench/*.py; do echo "== $$b"; python $$b || exit 1; done
clean:
	rm -rf build install log .venv
