#!/usr/bin/env bash
# What tests/test_viewer.py needs, installed when missing (make test runs this first):
#
#   * Debian's chromium (apt-get, only as root; nothing when it is on PATH already);
#   * viewer/node_modules: `npm ci` of viewer/package-lock.json, which pins Foxglove
#     Studio's prebuilt web bundle (@foxglove/studio-base 1.48.0) and React 17 by
#     version and integrity hash (npm refuses a tarball whose hash differs). It runs
#     again only when the lock file is newer than the last install.
#
# It never fails: without a registry, or without root for apt-get, it says what is
# missing and exits 0, and the viewer tests skip with that reason (pytest -rs).
set -u

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VIEWER=$ROOT/viewer
STAMP=$VIEWER/node_modules/.densityloop-installed
LOG=$(mktemp -t viewer_deps.XXXXXX)
trap 'rm -f "$LOG"' EXIT

say() { echo "viewer_deps: $*"; }

if ! command -v chromium >/dev/null 2>&1; then
    if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1; then
        say "installing Debian's chromium (apt-get)"
        if ! { timeout 600 apt-get update -qq &&
            DEBIAN_FRONTEND=noninteractive timeout 900 apt-get install -y -qq \
                --no-install-recommends chromium; } >"$LOG" 2>&1; then
            head -n 3 "$LOG" | sed 's/^/viewer_deps:   /'
            say "could not install chromium: the real-viewer tests will skip"
        fi
    else
        say "chromium missing (install Debian's chromium as root): the real-viewer tests will skip"
    fi
fi

if [[ -f $STAMP && ! $VIEWER/package-lock.json -nt $STAMP ]]; then
    exit 0
fi
if ! command -v npm >/dev/null 2>&1; then
    say "npm missing: the real-viewer tests will skip"
    exit 0
fi
say "npm ci in viewer/ (Foxglove Studio 1.48 web bundle, about 36 MB)"
if (cd "$VIEWER" && timeout 600 npm ci --ignore-scripts --no-audit --no-fund \
    --fetch-retries=1 --loglevel=error) >"$LOG" 2>&1; then
    touch "$STAMP"
else
    head -n 3 "$LOG" | sed 's/^/viewer_deps:   /'
    rm -rf "$VIEWER/node_modules"  # nothing half-installed: the tests skip
    say "npm ci failed: the real-viewer tests will skip"
fi
exit 0
