# Set-up is part of every target: a fresh clone needs only python3.11 and the package registry.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# The node runs on the CPU: torch comes from PyTorch's CPU index (one 0.19 GB wheel; on Linux PyPI's torch of
# the same version is 2.7 GB of wheels with its CUDA libraries, which the node never loads). TORCH_INDEX=
# (empty) skips this step, e.g. behind a mirror that has no route to that index.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_PIN   := $(shell grep -E '^torch==' requirements.txt)

.PHONY: setup test test-fast demo docs lint lock clean cpu-torch

$(STAMP): requirements.txt setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(MAKE) --no-print-directory cpu-torch
	$(BIN)/pip install --quiet -r requirements.txt
	$(BIN)/pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

setup: $(STAMP)

cpu-torch:
ifneq ($(strip $(TORCH_INDEX)),)
	$(BIN)/pip install --quiet --retries 1 --timeout 30 --no-deps --index-url $(TORCH_INDEX) "$(TORCH_PIN)" \
	  || echo "note: $(TORCH_PIN) is not at $(TORCH_INDEX) for this platform; it comes from your package index" \
	          "instead (on Linux PyPI's build downloads 2.7 GB with CUDA libraries the node does not use)"
endif

lint: setup
	$(BIN)/ruff check .

# everything (the README's test command; CI's), with the 15 slowest tests named at the end
test: setup lint
	$(BIN)/pytest -q --durations=15

# the unit tests: no DDS, no ../shared/data, nothing slow (markers: pyproject.toml, applied in test/conftest.py)
test-fast: setup
	$(BIN)/pytest -q -m "not ros and not data and not slow"

demo: setup
	$(BIN)/nmnet demo

# the documentation site into site/ (strict: a broken link fails); `$(BIN)/mkdocs serve` to browse it
docs: setup
	$(BIN)/mkdocs build --strict

# to change a pin: edit it in requirements.txt, delete the file's generated last section, then `make lock`
# (installs the pins, then pins everything they bring in)
lock: setup
	$(BIN)/python scripts/lock.py

clean:
	rm -rf $(VENV) build *.egg-info site
