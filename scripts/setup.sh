#!/usr/bin/env bash
# Installs the system packages pregrasp needs on a fresh Debian/Ubuntu machine (as root or with
# sudo): Mesa's software Vulkan driver so that wgpu finds an adapter without a GPU, and, with
# --browser, Debian's Chromium for the dashboard's browser test. Idempotent: it installs only
# what is missing.
set -euo pipefail
want=(mesa-vulkan-drivers libvulkan1)
if [[ "${1:-}" == "--browser" ]]; then
  want+=(chromium)
fi
missing=()
for p in "${want[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  SUDO=""
  [[ $(id -u) -ne 0 ]] && SUDO="sudo"
  echo "setup: installing ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
if ! command -v cargo >/dev/null; then
  echo "setup: cargo not found; install Rust (https://rustup.rs) first" >&2
  exit 1
fi
