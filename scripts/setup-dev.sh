#!/usr/bin/env bash
# Installs what the tests need on a fresh Debian/Ubuntu machine: system libraries, then the package with its dev extras.
#   libusb-1.0-0: needed by `import open3d`;  chromium: the browser test of the viewer (Playwright drives
#   Debian's build; nothing is downloaded by Playwright itself).
set -euo pipefail
cd "$(dirname "$0")/.."
need=()
python3 - <<'PY' 2>/dev/null || need+=(libusb-1.0-0)
import ctypes.util, sys
sys.exit(0 if ctypes.util.find_library("usb-1.0") else 1)
PY
command -v chromium >/dev/null 2>&1 || need+=(chromium)
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if command -v apt-get >/dev/null 2>&1; then
    ($SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null) \
      || echo "warning: could not install ${need[*]}; tests that need them will skip or fail"
  else
    echo "warning: please install ${need[*]} with your package manager"
  fi
fi
# CI's versions come from the constraints file (the package metadata pins nothing exactly)
PIP_DISABLE_PIP_VERSION_CHECK=1 python3 -m pip install -q -c .ci/constraints.txt -e ".[dev]"
