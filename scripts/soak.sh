#!/usr/bin/env bash
# Soak test of the service (not in CI): `pregrasp serve` on a loopback port, a generated
# three-camera sequence (10 Hz each) replayed over HTTP in a loop (each replay restarts the
# stamps at 0), 20 decision clients, and issue 16's abuse in a loop. Prints the server's RSS
# at the start, at minutes 2 and 10 (or the end), its peak, and the frames accepted per minute
# (intake must never stall).
#
#   scripts/soak.sh [SECONDS=600] [PORT=18090]
#
# Only loopback addresses; every loop ends with the soak time.
set -euo pipefail
cd "$(dirname "$0")/.."
SOAK_S="${1:-600}"
PORT="${2:-18090}"
BASE="http://127.0.0.1:$PORT"
S="$BASE/api/v1"
PROFILE="${PROFILE:-debug}"
if [[ "$PROFILE" == release ]]; then cargo build --quiet --release --bin pregrasp; else cargo build --quiet --bin pregrasp; fi
BIN="target/$PROFILE/pregrasp"
WORK=$(mktemp -d)
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
if [[ -z "${XDG_RUNTIME_DIR:-}" ]]; then XDG_RUNTIME_DIR=$(mktemp -d); export XDG_RUNTIME_DIR; fi

echo "generating the sequence (3 cameras, 10 Hz, 300 frames, 320x240) ..."
"$BIN" generate --out "$WORK/seq" --objects box,can,mug --frames 300 --width 320 --height 240 --seed 3 >/dev/null 2>&1
SEQ="$WORK/seq/000000"

# the abuse's payloads
python3 - "$WORK" <<'EOF'
import base64, json, struct, sys, zlib
work = sys.argv[1]
def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xffffffff)
bomb = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 15000, 15000, 16, 0, 0, 0, 0)) \
    + chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + chunk(b"IEND", b"")
b64 = base64.b64encode(bomb).decode()
json.dump({"stamp_ns": 1, "depth": {"encoding": "png16", "data_base64": b64}}, open(f"{work}/bomb.json", "w"))
raw = base64.b64encode(struct.pack("<f", 0.8) * 64 * 48).decode()
json.dump({"stamp_ns": 9223372036854775807, "depth": {"encoding": "f32le", "data_base64": raw}}, open(f"{work}/maxstamp.json", "w"))
json.dump({"stamp_ns": 1000000000, "depth": {"encoding": "f32le", "data_base64": raw}}, open(f"{work}/small.json", "w"))
with open(f"{work}/slow.obj", "w") as f:
    f.write("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n" + "f 1 2 3\n" * 120000)
with open(f"{work}/quick.obj", "w") as f:
    f.write("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
EOF

RUST_LOG="${RUST_LOG:-warn}" "$BIN" serve --addr "127.0.0.1:$PORT" --data-dir "$WORK/data" --accept-truth \
    >"$WORK/server.log" 2>&1 &
SERVER=$!
PIDS=()
cleanup() {
    for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
    kill "$SERVER" 2>/dev/null || true
    wait 2>/dev/null || true
    rm -rf "$WORK"
}
trap cleanup EXIT
for _ in $(seq 1 100); do curl -sf "$BASE/healthz" >/dev/null && break; sleep 0.1; done

END=$(( $(date +%s) + SOAK_S ))
rss_mib() { awk '/VmRSS/ {printf "%.0f", $2 / 1024}' "/proc/$SERVER/status"; }
accepted() { curl -sf "$BASE/metrics" | awk '/^pregrasp_frames_accepted_total / {print $2}'; }

# the robot: the sequence replayed in real time, again and again (the stamps restart each time)
( while (( $(date +%s) < END )); do
      "$BIN" replay --data "$SEQ" --server "$BASE" --rate 1 --no-decisions >>"$WORK/replay.log" 2>&1 || echo "replay failed" >>"$WORK/replay.log"
  done ) &
PIDS+=($!)

# 20 planners asking about the first track
for _ in $(seq 1 20); do
    ( while (( $(date +%s) < END )); do
          id=$(curl -sf "$S/tracks" | grep -o '"id":[0-9]*' | head -1 | cut -d: -f2 || true)
          if [[ -n "$id" ]]; then
              curl -s -o /dev/null -X POST "$S/tracks/$id/decision" -H 'content-type: application/json' -d '{"n_samples": 300}'
          fi
          sleep 0.5
      done ) &
    PIDS+=($!)
done

# the abuse of issue 16, in a loop
CAM='{"intrinsics": {"width": 64, "height": 48, "k": [60,0,32,0,60,24,0,0,1]}, "mount": {"type": "stationary", "world_from_camera": {"rotation_xyzw": [0,0,0,1], "translation_m": [0,0,1]}}}'
( while (( $(date +%s) < END )); do
      j() { curl -s -o /dev/null -H 'content-type: application/json' "$@"; }
      j -X PUT "$S/cameras/abuse" -d "$CAM"
      j -X POST "$S/cameras/abuse/frames" --data-binary @"$WORK/maxstamp.json"
      j -X POST "$S/cameras/abuse/frames" --data-binary @"$WORK/bomb.json"
      j -X POST "$S/cameras/abuse/frames" --data-binary @"$WORK/small.json"
      curl -s -o /dev/null -X DELETE "$S/cameras/abuse"
      j -X POST "$S/odometry" -d '{"stamp_ns": 1, "odom_from_base": {"pose": {"rotation_xyzw": [0,0,0,1], "translation_m": [1e308,0,0]}}}'
      j -X POST "$S/tracks" -d '{"object_id": "can", "world_from_object": {"rotation_xyzw": [0,0,0,1], "translation_m": [1e300,0,0]}}'
      j -X POST "$S/tracks" -d '{"object_id": "can", "world_from_object": {"rotation_xyzw": [0,0,0,1], "translation_m": [0.1,0,0.8]}}'
      j -X POST "$S/truth" -d "{\"stamp_ns\": 1, \"objects\": [{\"object\": \"$(head -c 3000 /dev/zero | tr '\0' x)\", \"world_from_object\": {\"rotation_xyzw\": [0,0,0,1], \"translation_m\": [0,0,0]}}]}"
      curl -s -o /dev/null -X PUT "$S/objects/abuse?format=obj&name=$(head -c 3000 /dev/zero | tr '\0' n)" --data-binary @"$WORK/quick.obj"
      curl -s -o /dev/null -X PUT "$S/objects/abuse?format=obj" --data-binary @"$WORK/slow.obj"
      curl -s -o /dev/null -X PUT "$S/objects/abuse?format=obj" --data-binary @"$WORK/quick.obj"
      curl -s -o /dev/null -X DELETE "$S/objects/abuse"
      curl -s -o /dev/null "$S/tracks/1/samples?n=-1"
      sleep 2
  done ) &
PIDS+=($!)

START=$(date +%s)
RSS0=$(rss_mib); PEAK=$RSS0; RSS2=""; LAST=$(accepted); STALLS=0
echo "start: RSS $RSS0 MiB"
while (( $(date +%s) < END )); do
    sleep 10
    r=$(rss_mib); (( r > PEAK )) && PEAK=$r
    t=$(( $(date +%s) - START ))
    if (( t % 60 < 10 )); then
        a=$(accepted); per_min=$(( a - LAST )); LAST=$a
        (( per_min == 0 )) && STALLS=$((STALLS + 1))
        echo "minute $(( t / 60 )): RSS $r MiB, frames accepted in the last minute $per_min"
        (( t / 60 == 2 )) && RSS2=$r
    fi
done
END_RSS=$(rss_mib)
echo "end: RSS $END_RSS MiB; peak $PEAK MiB; minute 2: ${RSS2:-n/a} MiB; minutes without intake: $STALLS"
if [[ -n "$RSS2" ]]; then
    echo "growth from minute 2 to the end: $(awk -v a="$RSS2" -v b="$END_RSS" 'BEGIN {printf "%.1f", (b - a) / a * 100}') %"
fi
echo "replays: $(grep -c '"frames_sent"' "$WORK/replay.log" || true) done, $(grep -c 'replay failed' "$WORK/replay.log" || true) failed"
grep -m 3 -i "error\|panick" "$WORK/server.log" || true
