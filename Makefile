# esa: the two user-facing commands are `make demo` and `make test`; both set
# everything up from a fresh clone (Rust release build + Python venv).
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CARGO ?= cargo
SERVER_BIN := $(CURDIR)/target/release/esa-server
# The Python client and tests use exactly the binary this Makefile built.
export ESA_SERVER_BIN := $(SERVER_BIN)
# MuJoCo renders headless through EGL (no display on CI machines).
export MUJOCO_GL ?= egl

PY_PACKAGES := client-py experiments tests
PY_LINT := $(PY_PACKAGES) server-py bench deploy/container tools/docs
# rllib: Ray RLlib, so that make test also runs the RLlib tests (client-py/tests/test_rllib*.py).
PY_EXTRAS := -e "client-py[sb3,zenoh,rllib,zoo,compare,dev,docs]" -e "experiments[dev]"

.PHONY: help setup build venv demo test test-rust test-python test-node lint buf fmt bench soak clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

setup: build venv ## build the server and create the Python venv

build: ## cargo build --release (esa-server and friends)
	$(CARGO) build --release --workspace --bins

venv: $(VENV)/.installed ## create .venv with esa_client, esa_experiments and their deps

$(VENV)/.installed: client-py/pyproject.toml experiments/pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(PY_EXTRAS)
	touch $@

demo: setup ## train PPO vs ESAPPO on InvertedPendulum-v5, plot and tabulate
	$(PY) client-py/examples/demo.py

test: venv test-rust test-python test-node ## set up, then run every Rust, Python and Node test

# `cargo test` also builds target/release/esa-server, which the Python tests use. A
# separate `cargo build` first would compile zenoh and its dependents twice: the test
# build unifies features from dev-dependencies (rand, zerocopy, regex) differently.
test-rust:
	$(CARGO) test --release --workspace

test-python:
	$(PY) -m pytest $(PY_PACKAGES)

# A second language: examples/node (@grpc/grpc-js) runs a session against the server built
# above. Skipped, saying so, where node or npm is missing.
test-node:
	@if command -v node >/dev/null && command -v npm >/dev/null; then \
		cd examples/node && npm ci --no-audit --no-fund --silent && node session.js; \
	else echo "test-node: SKIPPED: node/npm not found (Node.js >= 18 runs examples/node)"; fi

# The proto as a public API: buf lint (STANDARD) and buf breaking against the image of the last
# release's proto (tools/buf/esa-v1-release.binpb; at a release: make buf-baseline). buf comes
# from npm (tools/buf/package-lock.json); skipped, saying so, where npm is missing.
BUF := tools/buf/node_modules/.bin/buf
buf:
	@if command -v npm >/dev/null; then \
		(cd tools/buf && npm ci --no-audit --no-fund --silent) && \
		$(BUF) lint && $(BUF) breaking --against tools/buf/esa-v1-release.binpb && \
		echo "buf: lint and breaking-change check passed"; \
	else echo "buf: SKIPPED: npm not found (it installs @bufbuild/buf)"; fi

.PHONY: crates-check
# esa-proto needs esa-core and esa-client needs esa-proto from crates.io once published; until
# then cargo packages and verifies them together (publish in this order). Not in make test.
crates-check: ## cargo package (and verify) the publishable crates esa-core, esa-proto, esa-client
	$(CARGO) package -p esa-core -p esa-proto -p esa-client

.PHONY: buf-baseline
buf-baseline: ## at a release: the proto as released becomes buf breaking's baseline
	cd tools/buf && npm ci --no-audit --no-fund --silent
	$(BUF) build -o tools/buf/esa-v1-release.binpb

lint: venv ## rustfmt, clippy -D warnings, ruff, mypy --strict, gRPC stubs, k8s schemas, docs --strict
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy --release --workspace --all-targets -- -D warnings
	$(VENV)/bin/ruff check $(PY_LINT)
	$(VENV)/bin/ruff format --check $(PY_LINT)
	$(VENV)/bin/mypy  # mypy.ini: --strict over client-py/src and experiments/src
	$(MAKE) proto-check
	$(MAKE) k8s-check
	$(MAKE) docs
	$(MAKE) buf

fmt: venv ## apply rustfmt and ruff format
	$(CARGO) fmt --all
	$(VENV)/bin/ruff format $(PY_LINT)

# ONLY=part,...: re-run those parts (core, server, python, training, rllib_scaling, sizes) and
# keep the others' results; MAX_RUNNERS=N caps the RLlib bench's env runners (bench/run.sh).
bench: setup ## run the benchmarks -> BENCHMARKS.md (ONLY=training,rllib_scaling: those parts; MAX_RUNNERS=N)
	PY=$(PY) CARGO=$(CARGO) bash bench/run.sh $(if $(ONLY),--only $(ONLY)) $(if $(MAX_RUNNERS),--max-runners $(MAX_RUNNERS))

soak: setup ## a few minutes of load with floods and faults, then the long fuzz run -> tests/soak/RESULTS.md
	PY=$(PY) CARGO=$(CARGO) bash tests/soak/run.sh

.PHONY: wheel
# What would be uploaded to PyPI, in dist/: an sdist and one manylinux wheel for each of
# esa-client (esa_client and its extension esa_client._native) and esa-server (server-py/: the
# executable, built with the size-optimised cargo profile `dist`, as ruff and uv ship theirs;
# `esa-client[server]` pulls it). zig links both binaries against the symbols of an old glibc
# (maturin --zig), so the tag says which hosts run them, not which host built them; auditwheel
# show checks every ELF file in each wheel against MANYLINUX.
MANYLINUX ?= manylinux_2_17
# zig-linked builds have their own target directory: target/release, which make build and the
# tests use, stays as it is.
WHEEL_TARGET_DIR ?= $(CURDIR)/target/zig
WHEEL_PROJECTS := client-py server-py
# The release tools live in a venv of their own: building a wheel touches nothing in .venv.
RELEASE_VENV := .venv-release
$(RELEASE_VENV)/.installed: tools/release/requirements.txt
	test -x $(RELEASE_VENV)/bin/python || $(PYTHON) -m venv $(RELEASE_VENV)
	$(RELEASE_VENV)/bin/python -m pip install --quiet -r $<
	touch $@
# maturin --zig runs zig as `python3 -m ziglang`: the release venv's python3 must come first.
MATURIN := PATH="$(CURDIR)/$(RELEASE_VENV)/bin:$$PATH" CARGO_TARGET_DIR=$(WHEEL_TARGET_DIR) \
	$(CURDIR)/$(RELEASE_VENV)/bin/maturin

wheel: $(RELEASE_VENV)/.installed ## build dist/: sdists and manylinux wheels of esa-client and esa-server, checked
	rm -rf dist/esa_client-* dist/esa_server-*
	for project in $(WHEEL_PROJECTS); do \
		(cd $$project && $(MATURIN) build --zig --compatibility $(MANYLINUX) --out $(CURDIR)/dist && \
			$(MATURIN) sdist --out $(CURDIR)/dist) || exit 1; \
	done
	for wheel in dist/esa_client-*.whl dist/esa_server-*.whl; do \
		$(RELEASE_VENV)/bin/auditwheel show $$wheel | tee dist/auditwheel.txt && \
		grep -q '"$(MANYLINUX)_x86_64"' dist/auditwheel.txt || exit 1; \
	done
	rm dist/auditwheel.txt
	$(RELEASE_VENV)/bin/twine check --strict dist/esa_client-* dist/esa_server-*
	@ls -l dist/esa_client-* dist/esa_server-*

.PHONY: sdist-check
# Not part of `make test`: builds the extension from the sdist (cargo, a few minutes) in a clean venv.
sdist-check: ## make wheel, then pip install the client's sdist (built with cargo) in a clean venv, import it
	$(MAKE) wheel
	$(PYTHON) client-py/scripts/sdist_check.py

.PHONY: proto proto-check deps-check
# The Python stubs' generator is pinned (scripts/gen_proto.py GENERATOR): the oldest grpcio-tools,
# whose output sets the dependency floors. It wants protobuf < 5, so it lives in its own venv.
PROTO_VENV := .venv-proto
$(PROTO_VENV)/.installed: client-py/scripts/gen_proto.py
	test -x $(PROTO_VENV)/bin/python || $(PYTHON) -m venv $(PROTO_VENV)
	$(PROTO_VENV)/bin/python -m pip install --quiet "grpcio-tools==$$(sed -n 's/^GENERATOR = "\(.*\)"/\1/p' $<)"
	touch $@

proto: $(PROTO_VENV)/.installed ## regenerate the committed Python stubs (client-py's messages) with the pinned generator
	$(PROTO_VENV)/bin/python client-py/scripts/gen_proto.py

proto-check: $(PROTO_VENV)/.installed ## fail if the committed gRPC stubs differ from the generator's output
	$(PROTO_VENV)/bin/python client-py/scripts/gen_proto.py --check

# Not part of `make test`: downloads from PyPI (the oldest grpcio/protobuf; tensorboard, wandb).
deps-check: ## the client's tests at the declared dependency minimums; resolves beside tensorboard + wandb
	$(PYTHON) client-py/scripts/deps_check.py

.PHONY: docs
# --strict fails on a link or image mkdocs cannot resolve (mkdocs.yml: validation);
# check_site.py then reads the built HTML, where links of raw HTML and of hooks are too.
docs: venv ## build the docs site into site/ (mkdocs build --strict) and check every internal link and image
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet
	$(PY) tools/docs/check_site.py site

.PHONY: container container-check k8s-check
CONTAINER_IMAGE ?= localhost/esa-server:$(shell sed -n '/^\[workspace.package\]/,/^\[/s/^version = "\(.*\)"/\1/p' Cargo.toml)
# podman: run the image; chroot: only its filesystem, for sandboxes that refuse to start containers.
CONTAINER_MODE ?= podman
container: ## build the FROM scratch esa-server image with podman (deploy/container/build.sh)
	deploy/container/build.sh $(CONTAINER_IMAGE)

container-check: container venv ## start the image, check health SERVING, a Probe/Report round trip, metrics, uid
	$(PY) deploy/container/smoke_test.py --image $(CONTAINER_IMAGE) --mode $(CONTAINER_MODE)

$(RELEASE_VENV)/.k8s: $(RELEASE_VENV)/.installed
	$(RELEASE_VENV)/bin/python -m pip install --quiet "kubernetes-validate>=1.30"
	touch $@

# The oldest Kubernetes the manifests support (the pod-index label) and the newest schema known.
k8s-check: $(RELEASE_VENV)/.k8s ## validate deploy/k8s/*.yaml strictly against the Kubernetes schemas
	$(RELEASE_VENV)/bin/kubernetes-validate --quiet --strict -k 1.28.0 deploy/k8s/*.yaml
	$(RELEASE_VENV)/bin/kubernetes-validate --quiet --strict deploy/k8s/*.yaml

.PHONY: wheel-check
# Not part of `make test`: the clean venv downloads torch and stable-baselines3 from PyPI.
wheel-check: ## make wheel; in a clean venv without Rust: esa-client[sb3] runs README's snippet, then [server]
	$(PYTHON) client-py/scripts/wheel_check.py

clean: ## remove build outputs and the venv
	$(CARGO) clean
	rm -rf $(VENV) .venv-proto .venv-release site dist deploy/container/rootfs
