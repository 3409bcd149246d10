# The two README commands: `make demo` (a docking run in simulation) and `make test` (the
# whole test suite). Each installs the Debian packages it needs first (idempotent).
#   make demo [GUI=1]   a whole docking trial in simulation through ROS (headless; GUI=1: RViz)
#   make test           fmt check + clippy + cargo tests + rostest (tests/ros/*.test) + two
#                       machines in network namespaces (as root) + the package in a fresh
#                       catkin workspace beside a stand-in lbr_msgs
#   make screenshot     RViz under Xvfb during a sim trial -> out/rviz.png
SHELL := /bin/bash
ENV := source scripts/env.sh &&
CARGO_FLAGS ?= --release
GUI ?= 0

.PHONY: deps prebuild-check build demo test lint cargo-test rostest two-machines catkin-check screenshot bench clean

# The Debian packages, and beside them the crates' download and release build (they need none
# of the packages: scripts/prebuild-crates), so that a fresh machine does both at once.
deps:
	@scripts/install-deps & packages=$$!; scripts/prebuild-crates; wait $$packages

# The package in the catkin workspace target/catkin_ws (catkin_make: the nodes through cargo,
# release, in the checkout's target/; the messages through genmsg); env.sh sources its devel space.
build: deps
	@scripts/catkin-devel

demo: build
	@$(ENV) GUI=$(GUI) scripts/demo

lint: deps
	@$(ENV) cargo fmt --check
	@$(ENV) cargo clippy $(CARGO_FLAGS) --all-targets -- -D warnings -W clippy::too_many_lines

cargo-test: deps
	@$(ENV) cargo test $(CARGO_FLAGS) --no-fail-fast

rostest: build
	@scripts/run-rostest

# The estimator on one machine, simulator and controller on another: two network namespaces
# joined by a veth pair (root; skipped with the reason otherwise; docs/lab.md "Two machines").
two-machines: build
	@scripts/two-machines

# The package in a fresh catkin workspace beside a stand-in lbr_msgs: catkin_lint, devel and
# install spaces, a docking from sim.launch, one rostest through catkin_make run_tests.
catkin-check: build
	@scripts/catkin-check

# The release build of the nodes, checked to find every dependency already compiled by
# scripts/prebuild-crates (beside the packages' install), then the tests.
prebuild-check: deps
	@$(ENV) scripts/prebuild-crates --check

test: lint prebuild-check cargo-test rostest two-machines catkin-check

screenshot: build
	@$(ENV) scripts/screenshot

bench: deps
	@$(ENV) cargo build $(CARGO_FLAGS) --bin trocar_docking && target/release/trocar_docking bench --suite all

clean:
	cargo clean
