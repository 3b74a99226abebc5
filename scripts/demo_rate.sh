#!/usr/bin/env bash
# The live demo's step rate and stage table: starts `serve --demo` (release build), waits until
# its three objects' codebooks are ready (from DATA_DIR's cache when it has them), then reads
# `/metrics` before and after a window of SECONDS (default 168: six loops of the robot's 28 s
# drive, so that every phase of the loop counts once) and prints the differences: steps, seconds
# of stepping and per stage (stages of tracks updated side by side overlap, so they can add
# up to more than the stepping).
#
#   scripts/demo_rate.sh [SECONDS] [DATA_DIR]     (DATA_DIR default: a new temporary folder)
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_WINDOW="${1:-168}"
DATA_DIR="${2:-$(mktemp -d)}"
mkdir -p "$DATA_DIR"
PORT="${PORT:-18080}"
cargo build --release --quiet
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
target/release/pregrasp serve --demo --addr "127.0.0.1:$PORT" --data-dir "$DATA_DIR" >"$DATA_DIR/serve.log" 2>&1 &
SERVER=$!
trap 'kill -INT $SERVER 2>/dev/null || true; wait $SERVER 2>/dev/null || true' EXIT
for _ in $(seq 1 360); do
  sleep 5
  # objects whose 5-degree codebook is ready
  # (curl fails until the server listens: the parser then reads nothing and says 0)
  ready=$({ curl -s "127.0.0.1:$PORT/api/v1/objects" || true; } | python3 -c '
import json, sys
def fine(v):
    if isinstance(v, dict):
        if v.get("status") == "ready" and v.get("grid_step_deg") == 5:
            return True
        return any(fine(w) for w in v.values())
    return isinstance(v, list) and any(fine(w) for w in v)
try:
    d = json.load(sys.stdin)
    objects = d if isinstance(d, list) else next(v for v in d.values() if isinstance(v, list))
    print(sum(1 for o in objects if fine(o)))
except Exception:
    print(0)
')
  [[ "$ready" -ge 3 ]] && break
done
sleep 10
metrics() {
  curl -s "127.0.0.1:$PORT/metrics" \
    | grep -E '^pregrasp_(steps_total|step_seconds_total|step_stage_seconds_total|after_step_seconds_total)'
}
metrics >"$DATA_DIR/before.txt"
sleep "$SECONDS_WINDOW"
metrics >"$DATA_DIR/after.txt"
paste "$DATA_DIR/before.txt" "$DATA_DIR/after.txt" | awk -v w="$SECONDS_WINDOW" '
  { d = $4 - $2; printf "%-60s %12.3f\n", $1, d }
  $1 == "pregrasp_steps_total" { steps = d }
  $1 == "pregrasp_step_seconds_total" { busy = d }
  END { if (steps > 0) printf "rate %.2f Hz, %.1f ms of stepping a step\n", steps / w, 1e3 * busy / steps }'
