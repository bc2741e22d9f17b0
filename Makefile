# Fresh-machine entry points: `make demo` and `make test` each create .venv and install first.
#   make install       .venv with massview and its runtime dependencies (+ EGL/Mesa via .ci/system-deps)
#   make install-test  adds the test dependencies (pytest, hypothesis, playwright) and Chromium (.ci/test-deps)
# Every pip install is constrained by constraints.txt: a fresh install resolves the versions it was tested with.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP_FLAGS ?= -q
PIP := $(PY) -m pip install $(PIP_FLAGS) -c constraints.txt

.PHONY: install install-test system-deps test-deps test demo bench constraints clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt
	@bash .ci/system-deps
	python3 -m venv $(VENV)
	$(PIP) --upgrade pip
	$(PIP) -e .
	@touch $@

install-test: $(VENV)/.installed-test

$(VENV)/.installed-test: $(VENV)/.installed
	@bash .ci/test-deps
	$(PIP) -e '.[test]'
	@touch $@

system-deps:
	@bash .ci/system-deps

test-deps:
	@bash .ci/test-deps

test: install-test
	$(PY) -m pytest

demo: install
	$(VENV)/bin/massview demo

bench: install
	$(VENV)/bin/massview bench composite

# regenerate the pins from a working .venv (after changing dependencies in pyproject.toml)
constraints: install-test
	{ head -2 constraints.txt; $(PY) -m pip freeze --all --exclude-editable | grep -v -i -E '^(massview|setuptools)==' | grep -v '^#'; } > constraints.txt.new
	mv constraints.txt.new constraints.txt

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache
