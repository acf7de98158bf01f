# The two commands of the README quick start. Each creates or updates .venv.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.skyfit-installed

.PHONY: demo test bench venv clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

# torch==2.13.0 first: on the project's machines pip takes the local CPU wheel;
# a bare "torch" requirement would pull several GB of CUDA packages.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install --disable-pip-version-check -q "torch==2.13.0"
	$(BIN)/pip install --disable-pip-version-check -q -e ".[test]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/skyfit demo --out demo_out

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 tests

bench: $(STAMP)
	$(BIN)/skyfit bench --out docs/bench

clean:
	rm -rf $(VENV) demo_out
