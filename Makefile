# dh2rt: `make demo` runs the main job, `make test` runs every check, `make test-long` the long sweeps.
# Both create .venv and install what they need on a machine that has only Python 3.11.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-dev

.PHONY: demo test test-long bench lint typecheck contracts clean venv

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

# The paper's results in one process, then the same caterpillar with one OS process per
# module over emulated infrared serial links, each driving its emulated Dynamixel servos
# whose joints are PyBullet joints. Needs no hardware and no SocketCAN.
demo: $(STAMP)
	$(BIN)/dh2rt demo
	$(BIN)/dh2rt --transport serial --module-count 8 --cycles 300

# Tests that keep no real time run on two xdist workers; then the ones marked realtime (modules
# running in real time, timing judged against a bare loop measured in the same run:
# tests/conftest.py) run in a group of their own, two at a time in make test (a loop run mostly
# waits for its cycles; each must bear a busy core beside it anyway), one at a time in make
# test-long (whole reconfigurations in the loop). The docs' examples among them run one at a
# time after the rest: they are shell commands with no hil.pace to judge a slow run against a
# bare loop, and two CI runs lost links or a cycle in a doc example beside a flash's loop run.
# --durations: the slowest tests of each group, for whoever keeps make test within 10 minutes.
# The CPU group's tests marked slow start first (tests/conftest.py), and a worker that runs out
# of tests takes some of the other's (worksteal): the group does not end on one long test.
CPU_TESTS := $(BIN)/python -m pytest -q -n 2 --dist worksteal --durations=15
REALTIME_TESTS := $(BIN)/python -m pytest -q -n 2 --durations=25
REALTIME_LONG_TESTS := $(BIN)/python -m pytest -q -p no:xdist --durations=25

# tshark checks the Wireshark dissector (tests/tools/test_wireshark.py); installed here when
# missing and we are root, otherwise that test skips and says why
test: $(STAMP)
	@command -v tshark >/dev/null 2>&1 || [ "$$(id -u)" != 0 ] || DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends tshark >/dev/null || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends tshark >/dev/null) || echo "tshark is not installed: tests/tools/test_wireshark.py will skip"
	$(CPU_TESTS) -m "not realtime and not long"
	$(REALTIME_TESTS) -m "realtime and not long" --ignore=tests/docs
	$(REALTIME_LONG_TESTS) -m "realtime and not long" tests/docs
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

# The sweeps that make test keeps one case of: many seeds, whole reconfigurations in the loop.
# pytest exits 5 when a group selects no test: that group is empty, not failed.
test-long: $(STAMP)
	$(CPU_TESTS) -m "long and not realtime" || [ $$? = 5 ]
	$(REALTIME_LONG_TESTS) -m "long and realtime" || [ $$? = 5 ]

bench: $(STAMP)
	$(BIN)/python -m benchmarks

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache
