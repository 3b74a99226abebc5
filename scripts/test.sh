#!/usr/bin/env bash
# Runs every test: installs what the tests need (software Vulkan for wgpu, Chromium for the
# dashboard's browser test, openapi-python-client for the generated client's test), then `cargo test` over the library, binary, integration tests and
# doc tests, and checks that the benchmarks still build.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --browser --python-client
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
# lavapipe complains on every adapter request when XDG_RUNTIME_DIR is unset; harmless but noisy
if [[ -z "${XDG_RUNTIME_DIR:-}" ]]; then XDG_RUNTIME_DIR=$(mktemp -d); export XDG_RUNTIME_DIR; fi
# CI's disk is small and shared: no incremental state (about 3 GB it never reuses), and test
# binaries without debug info (about 45 of each binary's 50 MB; a panic still names its line)
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
export CARGO_PROFILE_DEV_DEBUG="${CARGO_PROFILE_DEV_DEBUG:-false}"
export CARGO_PROFILE_DEV_STRIP="${CARGO_PROFILE_DEV_STRIP:-debuginfo}"
cargo test --locked --all-targets --no-run
cargo test --locked
