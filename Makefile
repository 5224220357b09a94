# Two set-up commands (see README): `make demo` and `make test`.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo gui test bench clean

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e '.[test]'   # test = gui + cvxpy + test tools
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/labbench run demo --out sessions

gui: $(STAMP)
	$(VENV)/bin/labbench gui

test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(VENV)/bin/pytest -q

bench: $(STAMP)
	for f in bench/bench_*.py; do $(VENV)/bin/python $$f || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache
