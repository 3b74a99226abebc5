#!/usr/bin/env bash
# The main job: the service with its built-in demo scene and the dashboard, on
# http://127.0.0.1:8080/ (pass other `serve` options after the script, e.g. --addr 0.0.0.0:8080 --token-file FILE:
# beyond loopback a token is required unless --insecure).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
# lavapipe complains on every adapter request when XDG_RUNTIME_DIR is unset; harmless but noisy
if [[ -z "${XDG_RUNTIME_DIR:-}" ]]; then XDG_RUNTIME_DIR=$(mktemp -d); export XDG_RUNTIME_DIR; fi
exec cargo run --locked --release -- serve --demo "$@"
