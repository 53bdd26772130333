# Two entry points: `make demo` and `make test`. Both set up everything first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: demo test docs setup system bench bench-quick clean vendor-live

setup: $(STAMP)

system:
	bash scripts/install-system-deps.sh

$(STAMP): pyproject.toml Makefile scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check --upgrade pip
	$(BIN)/python -m pip install -q --disable-pip-version-check -e '.[test,fab,docs]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/softphantom demo --out $(OUT)/demo --overwrite

test: $(STAMP) docs
	$(BIN)/python -m pytest -n 2 --dist loadfile softphantom tests

# the documentation site (out/site); --strict: a broken link, anchor or API reference fails
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# the accuracy studies' bounds at the sizes they were measured at (a few minutes; `make bench` starts with them)
bench-quick: $(STAMP)
	for b in benchmarks/bench_interpolants.py benchmarks/bench_shipped_atlas.py; do \
		echo "== $$b --quick"; $(BIN)/python $$b --quick || exit 1; done

bench: bench-quick
	$(BIN)/python -m pip install -q --disable-pip-version-check -e '.[pardiso]'
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done
	$(BIN)/python benchmarks/render_docs.py

# the live page's three.js and uPlot (committed; this refreshes them from the npm registry)
vendor-live:
	bash scripts/vendor-live.sh

clean:
	rm -rf $(VENV) $(OUT) build *.egg-info
