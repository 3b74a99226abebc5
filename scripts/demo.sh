#!/usr/bin/env bash
# The main job: the service with its built-in demo scene and the dashboard, on
# http://127.0.0.1:8080/ (pass other `serve` options after the script, e.g. --addr 0.0.0.0:8080).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
exec cargo run --locked --release -- serve --demo "$@"
