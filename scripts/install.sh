#!/usr/bin/env bash
# Installs gpdepth3d from this checkout with an extra (default: all), at CI's versions (.ci/constraints.txt),
# after the system library Open3D loads (libusb-1.0-0) when it is missing; with "dev" also Debian's chromium
# (the viewer's browser test; Playwright downloads nothing).
#   bash scripts/install.sh          # everything the README uses
#   bash scripts/install.sh dev      # and the test tools
set -euo pipefail
cd "$(dirname "$0")/.."
extra="${1:-all}"
need=()
python3 - <<'PY' 2>/dev/null || need+=(libusb-1.0-0)
import ctypes.util, sys
sys.exit(0 if ctypes.util.find_library("usb-1.0") else 1)
PY
if [ "$extra" = "dev" ]; then command -v chromium >/dev/null 2>&1 || need+=(chromium); fi
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if command -v apt-get >/dev/null 2>&1; then
    ($SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null) \
      || echo "warning: could not install ${need[*]}; install them with your package manager"
  else
    echo "warning: please install ${need[*]} with your package manager"
  fi
fi
PIP_DISABLE_PIP_VERSION_CHECK=1 python3 -m pip install -q -c .ci/constraints.txt -e ".[$extra]"
