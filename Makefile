# Fresh-machine entry points: `make demo` and `make test` each create .venv and install first.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP_FLAGS ?= -q

.PHONY: install system-deps test demo bench clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@bash .ci/system-deps
	python3 -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) --upgrade pip
	$(PY) -m pip install $(PIP_FLAGS) -e '.[test]'
	@touch $@

system-deps:
	@bash .ci/system-deps

test: install
	$(PY) -m pytest

demo: install
	$(VENV)/bin/massview demo

bench: install
	$(VENV)/bin/massview bench composite

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache
