#!/usr/bin/env bash
# Installs the system packages pregrasp needs on a fresh Debian/Ubuntu machine (as root or with
# sudo): Mesa's software Vulkan driver so that wgpu finds an adapter without a GPU; with
# --browser, Debian's Chromium for the dashboard's browser test; with --python-client,
# openapi-python-client (pinned) in a virtual environment under target/ for the generated
# client's test (tests/api/python_client.rs; needs python3 with venv). Idempotent: it installs
# only what is missing, and returns at once when everything is there.
set -euo pipefail
cd "$(dirname "$0")/.."
# the generator's version the test was written against (its output's layout changes between
# minor versions)
OPENAPI_PYTHON_CLIENT_VERSION=0.29.1
want=(mesa-vulkan-drivers libvulkan1)
python_client=0
for arg in "$@"; do
  case "$arg" in
    --browser) want+=(chromium) ;;
    --python-client) python_client=1 ;;
    *) echo "setup: unknown option $arg (--browser, --python-client)" >&2; exit 2 ;;
  esac
done
if ((python_client)); then
  want+=(python3 python3-venv)
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
if ((python_client)); then
  VENV=target/openapi-client-venv
  have=$("$VENV/bin/openapi-python-client" --version 2>/dev/null | awk '{print $NF}' || true)
  if [[ "$have" != "$OPENAPI_PYTHON_CLIENT_VERSION" ]]; then
    echo "setup: installing openapi-python-client $OPENAPI_PYTHON_CLIENT_VERSION into $VENV" >&2
    python3 -m venv --clear "$VENV"
    "$VENV/bin/pip" install --quiet --disable-pip-version-check "openapi-python-client==$OPENAPI_PYTHON_CLIENT_VERSION"
  fi
fi
