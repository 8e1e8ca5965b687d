#!/usr/bin/env bash
# Create ./.venv and install plantdyn with pinned dependencies (idempotent).
# Usage: scripts/setup.sh [--test]   (--test also installs the test extras, the
# software-Vulkan libraries the headless Rerun viewer test needs and Chromium, which
# screenshots report.html headless)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
want_test=0
[ "${1:-}" = "--test" ] && want_test=1

if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.plantdyn-installed
sig="$(cat pyproject.toml constraints.txt | sha256sum | cut -c1-16)-$want_test"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$sig" ]; then
  echo "[setup] installing pinned dependencies (first time takes a few minutes)"
  extras=""
  [ $want_test = 1 ] && extras="[test]"
  # (this machine's pip config lists optional local mirrors; their "is ignored" notes are noise)
  log=$(mktemp)
  if ! { .venv/bin/python -m pip install -q --upgrade pip &&
         .venv/bin/python -m pip install -q -c constraints.txt -e ".${extras}"; } >"$log" 2>&1; then
    grep -v "is ignored: it is neither a file nor a directory" "$log" >&2 || true
    echo "[setup] pip install failed (full log: $log)" >&2
    exit 1
  fi
  grep -v -e "is ignored: it is neither a file nor a directory" -e "editable" -e "WheelFile(wheel_path" -e "^ *!!" \
    -e "\*\*\*\*" -e "name as your package" -e "Please be careful" -e "^ *$" "$log" || true
  rm -f "$log"
  echo "$sig" > "$stamp"
fi

if [ $want_test = 1 ]; then
  # The headless viewer screenshot test renders with Mesa's software Vulkan driver.
  if ! ldconfig -p 2>/dev/null | grep -q libvulkan.so.1 || [ ! -d /usr/share/vulkan/icd.d ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      echo "[setup] installing libvulkan1 + mesa-vulkan-drivers (software Vulkan for the headless viewer test)"
      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libvulkan1 mesa-vulkan-drivers >/dev/null) \
        || echo "[setup] WARNING: could not install software Vulkan; the viewer screenshot test will fail"
    else
      echo "[setup] WARNING: not root; install libvulkan1 and mesa-vulkan-drivers for the viewer screenshot test"
    fi
  fi
  # The report.html test takes screenshots with headless Chromium (Debian's package).
  if [ ! -x /usr/bin/chromium ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      echo "[setup] installing chromium (headless screenshots of report.html)"
      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
        || echo "[setup] WARNING: could not install chromium; the report.html screenshot test will fail"
    else
      echo "[setup] WARNING: not root; install chromium for the report.html screenshot test"
    fi
  fi
fi
