# The two README commands: `make demo` (a docking run in simulation) and `make test` (the
# whole test suite). Each installs the Debian packages it needs first (idempotent).
SHELL := /bin/bash
ENV := source scripts/env.sh &&
CARGO_FLAGS ?= --release

.PHONY: deps build demo test lint cargo-test bench clean

deps:
	@scripts/install-deps

build: deps
	@$(ENV) cargo build $(CARGO_FLAGS) --bins

demo: build
	@$(ENV) scripts/demo

lint: deps
	@$(ENV) cargo fmt --check
	@$(ENV) cargo clippy $(CARGO_FLAGS) --all-targets -- -D warnings

cargo-test: deps
	@$(ENV) cargo test $(CARGO_FLAGS) --no-fail-fast

test: lint cargo-test

bench: deps
	@$(ENV) cargo bench

clean:
	cargo clean
