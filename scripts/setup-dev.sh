#!/usr/bin/env bash
# Installs what the tests need on a fresh Debian/Ubuntu machine: system libraries (libusb-1.0-0 for Open3D,
# chromium for the viewer's browser test), then the package with its [dev] extra at CI's versions.
set -euo pipefail
bash "$(dirname "$0")/install.sh" dev
