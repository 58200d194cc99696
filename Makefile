# Each target creates .venv when missing and installs the project into it.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo bench lint clean test-vcan bench-vcan

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	$(BIN)/cifemu demo

bench: $(STAMP)
	$(BIN)/python -m bench

# The SocketCAN tests (marker vcan) inside a Linux with vcan0: User-Mode Linux through
# tools/vcan-vm where this kernel has no SocketCAN, the host itself where it has vcan0.
VCAN_VM := tools/vcan-vm
VCAN_TIMEOUT ?= 1200

test-vcan: $(STAMP)
	$(VCAN_VM) --timeout $(VCAN_TIMEOUT) -- env CIFEMU_REQUIRE_SOCKETCAN=1 \
		$(BIN)/python -m pytest -q -m vcan

# The SocketCAN figures (bench.vcan: vcan0, the broadcast manager, the card on them).
bench-vcan: $(STAMP)
	$(VCAN_VM) --timeout $(VCAN_TIMEOUT) -- $(BIN)/python -m bench.vcan


lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
