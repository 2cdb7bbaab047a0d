# Set-up and the two everyday commands. `make run` runs the main job on the default config,
# `make test` runs the whole test suite; both install libtorch first if this machine lacks it.
#
# libtorch comes from PyPI's torch wheel, installed once into a virtualenv outside the repo
# (TORCH_VENV) and reused by every later build; torch-sys finds it through the `.libtorch` link
# (.cargo/config.toml), so plain cargo commands work too once `make` has run.

TORCH_VERSION := 2.13.0
TORCH_VENV ?= $(HOME)/.cache/uavmeta/torch-$(TORCH_VERSION)
CONFIG ?= configs/default.toml

# The compiled dependencies, kept beside libtorch: a clone without target/ (or python/target/)
# starts from a copy of the last build's (the ~600 dependency crates are 18 of a clean build's 20
# minutes on two cores); cargo rebuilds whatever differs, this clone's own crates always. The copy
# is refreshed after a build whenever its stamp changed: the compiler, the lock file, the
# manifest (profiles, patches) and the cargo config. TARGET_CACHE= (empty) turns both off.
TARGET_CACHE ?= $(HOME)/.cache/uavmeta/target

# $(call stamp,MANIFEST_DIR): what the compiled dependencies of the workspace there depend on,
# the patched crates of vendor/ included.
stamp = { rustc -V; cat $(1)/Cargo.lock $(1)/Cargo.toml .cargo/config.toml; \
	  find vendor -type f -print0 | sort -z | xargs -0 cat; } | cksum
# $(call from-cache,DIR,CACHE,MANIFEST_DIR,IF_SAME): DIR starts as a copy of CACHE if DIR is
# missing; then IF_SAME runs if the copy's stamp is this tree's.
from-cache = if [ -n "$(TARGET_CACHE)" ] && [ ! -d $(1) ] && [ -f "$(2)/stamp" ]; then \
	  echo "starting $(1)/ from the compiled dependencies in $(2)"; cp -a --reflink=auto "$(2)" $(1); \
	  if [ "$$($(call stamp,$(3)))" = "$$(cat "$(2)/stamp")" ]; then $(4) true; fi; fi
# The patched crates of vendor/ are path dependencies, which cargo judges by mtime: a clone's
# checkout time would rebuild the patched Zenoh link and the Zenoh crates above it (300 s of CPU)
# for no change. With the stamps equal, vendor/ is byte for byte what the copy was built from, and
# its files get an old mtime.
age-vendor = find vendor -exec touch -h -d @946684800 {} +;
# $(call to-cache,DIR,CACHE,MANIFEST_DIR): CACHE becomes a copy of DIR if its stamp changed, less
# the workspace's own products (half the size, and no other clone can use them). Copied to a new
# directory, then renamed into place, so a clone copying the old one never sees half of the new.
to-cache = stamp="$$($(call stamp,$(3)))"; \
	if [ -n "$(TARGET_CACHE)" ] && [ -d $(1) ] && [ "$$stamp" != "$$(cat "$(2)/stamp" 2>/dev/null)" ]; then \
	  echo "keeping the compiled dependencies in $(2)"; \
	  mkdir -p "$$(dirname "$(2)")" && rm -rf "$(2).new" && cp -a --reflink=auto $(1) "$(2).new" && \
	  { find "$(2).new" -maxdepth 3 -name '*uavmeta*' -exec rm -rf {} +; \
	    find "$(2).new" -maxdepth 3 -path '*/deps/*' -type f -perm -u+x ! -name '*.so' -delete; true; } && \
	  echo "$$stamp" > "$(2).new/stamp" && rm -rf "$(2)" && mv "$(2).new" "$(2)"; fi

.PHONY: run test build bench libtorch test-tools interop python wheel

run: build
	target/release/uavmeta launch --config $(CONFIG)

# The doc examples (which nextest does not run), then the suite under cargo-nextest where it is
# installed (.config/nextest.toml: every test in its own process, both cores busy across test
# binaries, the slowest first; about a fifth less wall time than `cargo test` on 2 cores,
# docs/TESTING.md). Without nextest, `cargo test` runs the same tests one binary after another.
test: libtorch test-tools interop python
	@$(call from-cache,target,$(TARGET_CACHE),.,$(age-vendor))
ifneq ($(shell command -v cargo-nextest),)
	cargo test --doc --workspace --release
	cargo nextest run --workspace --release --no-run
	@$(call to-cache,target,$(TARGET_CACHE),.)
	cargo nextest run --workspace --release
else
	@echo "cargo-nextest is not installed (cargo install cargo-nextest --locked): running cargo test"
	cargo test --workspace --release --no-run
	@$(call to-cache,target,$(TARGET_CACHE),.)
	cargo test --workspace --release
endif

build: libtorch
	@$(call from-cache,target,$(TARGET_CACHE),.,$(age-vendor))
	cargo build --release
	@$(call to-cache,target,$(TARGET_CACHE),.)

bench: libtorch
	cargo bench --workspace

# The link is remade every time, so a changed TORCH_VENV takes effect.
libtorch: $(TORCH_VENV)/.installed
	ln -sfn "$$($(TORCH_VENV)/bin/python -c 'import os, torch; print(os.path.dirname(torch.__file__))')" .libtorch

$(TORCH_VENV)/.installed:
	python3 -m venv $(TORCH_VENV)
	$(TORCH_VENV)/bin/pip install --no-input --disable-pip-version-check torch==$(TORCH_VERSION)
	touch $@

# Tools the end-to-end tests run, from Debian: tests/runtime.rs lints every /metrics answer with
# `promtool check metrics` and tests/dashboard.rs runs the `prometheus` server (both in the
# prometheus package); tests/terminal.rs watches a launch in tmux; tests/slurm.rs runs a one-node
# Slurm cluster (slurm-wlm: slurmctld, slurmd and the client commands; munge: munged, in sbin).
# Installed here where apt-get can (as root), and required when CI=true.
TEST_TOOLS := promtool prometheus tmux sbatch slurmctld slurmd munged
APT_INSTALL := DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends prometheus tmux slurm-wlm munge
HAVE_TEST_TOOLS := for tool in $(TEST_TOOLS); do PATH="$$PATH:/usr/sbin:/sbin" command -v $$tool >/dev/null || exit 1; done

test-tools:
	@( $(HAVE_TEST_TOOLS) ) || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
	  { $(APT_INSTALL) || { apt-get update -q && $(APT_INSTALL); }; } >/dev/null 2>&1; }; \
	( $(HAVE_TEST_TOOLS) ) || \
	  echo "missing some of: $(TEST_TOOLS) (Debian: prometheus, tmux, slurm-wlm, munge); the tests that need them skip"

# tests/interop.rs loads exported datasets with minari, d3rlpy and numpy themselves, pinned in
# tests/interop-requirements.txt and installed into the libtorch virtualenv; the constraint makes
# pip fail rather than replace torch. Without network they stay missing: the test skips, except
# under CI=true, where it fails.
INTEROP_REQUIREMENTS := tests/interop-requirements.txt

interop: $(TORCH_VENV)/.interop-installed

$(TORCH_VENV)/.interop-installed: $(INTEROP_REQUIREMENTS) $(TORCH_VENV)/.installed
	@echo 'torch==$(TORCH_VERSION)' > $(TORCH_VENV)/torch-constraint.txt
	@$(TORCH_VENV)/bin/pip install --no-input --disable-pip-version-check -q \
	  -c $(TORCH_VENV)/torch-constraint.txt -r $(INTEROP_REQUIREMENTS) && touch $@ || \
	  echo "the interop packages ($(INTEROP_REQUIREMENTS)) are not installed; tests/interop.rs skips"

# The Python package (python/, `import uavmeta`; PyO3, built by maturin) installed into the same
# virtualenv, where tests/python.rs runs its pytest suite against gymnasium, numpy and
# stable-baselines3. Installed again on every run: cargo rebuilds only what changed (python/target),
# so an unchanged package costs seconds. If it cannot be built the test skips, except under CI=true.
python: interop
	@$(call from-cache,python/target,$(TARGET_CACHE)-python,python)
	@if PATH="$(TORCH_VENV)/bin:$$PATH" $(TORCH_VENV)/bin/pip install --no-input --disable-pip-version-check -q \
	  --no-build-isolation --no-deps --force-reinstall ./python; \
	then $(call to-cache,python/target,$(TARGET_CACHE)-python,python); \
	else echo "the Python package (python/) is not installed; tests/python.rs skips"; fi

# A wheel of the Python package for every CPython >= 3.9 on this platform (PyO3's abi3), in
# target/wheels; it installs with pip into any virtualenv without a Rust toolchain
# (tests/python.rs installs it so). maturin comes from the interop requirements.
wheel: interop
	PATH="$(TORCH_VENV)/bin:$$PATH" maturin build --release -m python/Cargo.toml --out target/wheels
