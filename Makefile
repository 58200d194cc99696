# Each target creates .venv when missing and installs the project into it.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test test-fast demo bench lint clean test-vcan bench-vcan test-soak

# pip installs a pyproject project editable from 21.3 on (PEP 660): only an older pip is
# upgraded first, a download and an install fewer on every fresh clone. --no-compile: Python
# compiles a module when it is first imported, so the thousands nobody imports (mypy's,
# hypothesis's, pygments' lexers) are not compiled at all: 8 s of CPU less (docs/testing.md).
$(STAMP): pyproject.toml host_api/_devflags.c firmware/_mailbox.c dpm/_quicklock.c \
		host_api/cia309/_plainline.c
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -c 'import pip, sys; sys.exit([int(n) for n in pip.__version__.split(".")[:2]] < [21, 3])' \
		|| $(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -e '.[dev]'
	touch $(STAMP)

# The whole suite but the virtual machines' tests (make test-vcan): pytest-xdist spreads it
# over TEST_WORKERS processes, then the tests that measure time (marker serial) run alone,
# from their own modules only (collecting the whole suite again took 10 s).
# Before them, three independent jobs run side by side (make -j3): the venv, then ruff and
# mypy in it; libcif; libcifdev.so. The venv waits mostly on downloads, the builds on the
# compiler: on a fresh clone that takes about a minute off. docs/testing.md says which
# test runs where, and how long each part takes.
# Three workers on two cores: about half of a test's time is waiting on the card's timers and
# process starts, not CPU, so a third worker fills the other half (7.5 min for the parallel
# pass where two took 8.5-10, docs/testing.md).
TEST_WORKERS ?= 3

test:
	$(MAKE) --no-print-directory -j3 --output-sync=target lint build-libcif build-legacy
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal --durations=30 \
		-m 'not vcan_vm and not serial'
	$(BIN)/python -m pytest -q -m 'serial and not vcan_vm' $$($(BIN)/python -m tests.selection serial)

# The codec, parser and source tests (marker fast): no process, no socket served, no image
# mapped; under a minute.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m fast

demo: $(STAMP)
	$(BIN)/cifemu demo

bench: $(STAMP)
	$(BIN)/python -m bench

# The SocketCAN tests (marker vcan) inside a Linux with vcan0: User-Mode Linux through
# tools/vcan-vm where this kernel has no SocketCAN, the host itself where it has vcan0.
VCAN_VM := tools/vcan-vm
VCAN_TIMEOUT ?= 1200

# The soak benchmark's 1-minute form with its invariants (issue 13's CI form; 30 minutes by
# hand: python -m bench soak --minutes 30). .ci/run gives it a second try, because on a
# shared machine one late heartbeat of 126 nodes in a minute is the machine's, not the card's.
test-soak: $(STAMP)
	CIFEMU_SOAK_MINUTES=1 $(BIN)/python -m pytest -q tests/test_soak.py

# Then tools/vcan-vm's own tests on this host (marker vcan_vm: qemu without KVM, 2 minutes).
test-vcan: $(STAMP)
	$(VCAN_VM) --vcan 2 --timeout $(VCAN_TIMEOUT) -- env CIFEMU_REQUIRE_SOCKETCAN=1 \
		$(BIN)/python -m pytest -q -m vcan
	$(BIN)/python -m pytest -q -m vcan_vm

# The SocketCAN figures (bench.vcan: vcan0, the broadcast manager, the card on them, 309-3
# reads against CANopenNode's gateway where CANopenNode is built beside the project, and
# the CAN benchmark's phases with their nodes on vcan0), one JSON document on stdout. The
# guest sees only its own load: the host's goes in by the environment.
bench-vcan: $(STAMP)
	@$(VCAN_VM) --timeout $(VCAN_TIMEOUT) -- env CIFEMU_HOST_LOADAVG="$$(cut -d' ' -f1-3 /proc/loadavg)" \
		$(BIN)/python -m bench.vcan


lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache

# libcif (the C driver library) and its sanitized build, which the tests compile against.
build-libcif:
	$(MAKE) -C libcif all sanitize

# libcifdev.so (cifemu legacy) for x86-64 and i386. The i386 build needs gcc-multilib and
# libc6-i386: when they are missing and this runs as root with apt-get (CI), it installs
# them, saying so first; CIFEMU_NO_APT=1 installs nothing. Without them
# libcif/build/i386/MISSING says in one line what to install, and the i386 tests skip.
.PHONY: build-legacy
build-legacy:
	@if [ -z "$(CIFEMU_NO_APT)" ] \
	    && ! printf 'int main(void){return 0;}\n' | $(CC) -m32 -x c - -o /tmp/.cifemu-m32-probe 2>/dev/null \
	    && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo 'make: apt-get install gcc-multilib libc6-i386, for the i386 build of libcifdev.so (32-bit legacy binaries); make ... CIFEMU_NO_APT=1 installs nothing and skips the i386 tests'; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
	    gcc-multilib libc6-i386) >/dev/null || true; \
	fi; rm -f /tmp/.cifemu-m32-probe
	$(MAKE) -C libcif preload
