# The two README commands: `make demo` (a docking run in simulation) and `make test` (the
# whole test suite). Each installs the Debian packages it needs first (idempotent).
#   make demo [GUI=1]   a whole docking trial in simulation through ROS (headless; GUI=1: RViz)
#   make test           fmt check + clippy + cargo tests + rostest (tests/ros/*.test)
#   make screenshot     RViz under Xvfb during a sim trial -> out/rviz.png
SHELL := /bin/bash
ENV := source scripts/env.sh &&
CARGO_FLAGS ?= --release
PROFILE := $(if $(findstring --release,$(CARGO_FLAGS)),release,debug)
GUI ?= 0

.PHONY: deps build demo test lint cargo-test rostest screenshot bench clean

deps:
	@scripts/install-deps

# Node binaries, then the ROS view of the package (one profile's nodes) and Python messages.
build: deps
	@$(ENV) cargo build $(CARGO_FLAGS) --bins
	@scripts/ros-package $(PROFILE)

demo: build
	@$(ENV) GUI=$(GUI) scripts/demo

lint: deps
	@$(ENV) cargo fmt --check
	@$(ENV) cargo clippy $(CARGO_FLAGS) --all-targets -- -D warnings -W clippy::too_many_lines

cargo-test: deps
	@$(ENV) cargo test $(CARGO_FLAGS) --no-fail-fast

rostest: build
	@scripts/run-rostest

test: lint cargo-test rostest

screenshot: build
	@$(ENV) scripts/screenshot

bench: deps
	@$(ENV) cargo bench

clean:
	cargo clean
