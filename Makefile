# Set-up and the two everyday commands. `make run` runs the main job on the default config,
# `make test` runs the whole test suite; both install libtorch first if this machine lacks it.
#
# libtorch comes from PyPI's torch wheel, installed once into a virtualenv outside the repo
# (TORCH_VENV) and reused by every later build; torch-sys finds it through that interpreter.

TORCH_VERSION := 2.13.0
TORCH_VENV ?= $(HOME)/.cache/uavmeta/torch-$(TORCH_VERSION)
CONFIG ?= configs/default.toml

export VIRTUAL_ENV := $(TORCH_VENV)
export PATH := $(TORCH_VENV)/bin:$(PATH)
export LIBTORCH_USE_PYTORCH := 1

.PHONY: run test build bench libtorch test-tools env

run: build
	target/release/uavmeta launch --config $(CONFIG)

test: libtorch test-tools
	cargo test --workspace --release

build: libtorch
	cargo build --release

bench: libtorch
	cargo bench --workspace

libtorch: $(TORCH_VENV)/.installed

$(TORCH_VENV)/.installed:
	python3 -m venv $(TORCH_VENV)
	$(TORCH_VENV)/bin/pip install --no-input --disable-pip-version-check torch==$(TORCH_VERSION)
	touch $@

# Tools the end-to-end tests run, from Debian: tests/runtime.rs lints every /metrics answer with
# `promtool check metrics` and tests/dashboard.rs runs the `prometheus` server (both in the
# prometheus package); tests/terminal.rs watches a launch in tmux. Installed here where apt-get
# can (as root), and required when CI=true.
TEST_TOOLS := promtool prometheus tmux
APT_INSTALL := DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends prometheus tmux
HAVE_TEST_TOOLS := for tool in $(TEST_TOOLS); do command -v $$tool >/dev/null || exit 1; done

test-tools:
	@( $(HAVE_TEST_TOOLS) ) || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { $(APT_INSTALL) || { apt-get update -q && $(APT_INSTALL); }; } >/dev/null 2>&1; }; \
	( $(HAVE_TEST_TOOLS) ) || \
	  echo "missing some of: $(TEST_TOOLS) (Debian: prometheus, tmux); the tests that need them skip"

# `eval "$(make -s env)"` sets up a shell for plain cargo commands.
env:
	@echo 'export VIRTUAL_ENV=$(TORCH_VENV) LIBTORCH_USE_PYTORCH=1 PATH=$(TORCH_VENV)/bin:$$PATH'
