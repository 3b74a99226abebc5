#!/usr/bin/env bash
# Fuzzes the served OpenAPI document with schemathesis (an independent fuzzer): starts
# `pregrasp serve` on a loopback port with a fresh data folder, runs `schemathesis run` with a
# fixed seed and bounded examples, and stops the server. Exit status: schemathesis's.
#
#   scripts/schemathesis.sh [MAX_EXAMPLES=50] [PORT=18089]
#
# Needs Python 3.9+ and PyPI (the virtual environment is kept in target/schemathesis-venv).
set -euo pipefail
cd "$(dirname "$0")/.."
MAX_EXAMPLES="${1:-50}"
PORT="${2:-18089}"
SEED="${SCHEMATHESIS_SEED:-16}"
VENV=target/schemathesis-venv
if [[ ! -x "$VENV/bin/schemathesis" ]]; then
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install --quiet "schemathesis>=4.32,<5"
fi
cargo build --quiet --bin pregrasp
DATA=$(mktemp -d)
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
if [[ -z "${XDG_RUNTIME_DIR:-}" ]]; then XDG_RUNTIME_DIR=$(mktemp -d); export XDG_RUNTIME_DIR; fi
RUST_LOG="${RUST_LOG:-warn}" target/debug/pregrasp serve --addr "127.0.0.1:$PORT" --data-dir "$DATA" \
    --request-timeout-s 20 &
SERVER=$!
trap 'kill "$SERVER" 2>/dev/null; wait "$SERVER" 2>/dev/null; rm -rf "$DATA"' EXIT
for _ in $(seq 1 100); do
    curl -sf "http://127.0.0.1:$PORT/healthz" >/dev/null && break
    sleep 0.1
done
# run from the data folder: schemathesis keeps a cache of its findings in the working folder
ROOT=$(pwd)
cd "$DATA"
"$ROOT/$VENV/bin/schemathesis" run "http://127.0.0.1:$PORT/openapi.json" \
    --url "http://127.0.0.1:$PORT" \
    --checks not_a_server_error,response_schema_conformance,content_type_conformance,status_code_conformance \
    --seed "$SEED" \
    --max-examples "$MAX_EXAMPLES" \
    --request-timeout 30 \
    --generation-database :memory: \
    --no-color
