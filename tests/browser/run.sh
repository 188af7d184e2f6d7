#!/usr/bin/env bash
# The operator's screen tested in a real browser (README "Operator's screen"): builds cellsight (Release), prepares
# the small simulated cell (scripts/sim_cell.sh, cached in WORK/cell, the soak's cache when WORK is the soak's) and
# runs tests/browser/hmi_browser.mjs: Debian's Chromium, headless, driven by puppeteer-core, against `cellsight run
# --sim` with an acknowledging PLC. A stage of scripts/test.sh (CELLSIGHT_BROWSER=0 skips it there).
# Missing tools (chromium, node, puppeteer-core) fail the test with the fix: scripts/setup.sh installs them.
#
# usage: tests/browser/run.sh [--build DIR] [--work DIR] [ARGUMENTS of hmi_browser.mjs, e.g. --only live --keep]
#   --build DIR  the Release build folder (default build); screenshots go to DIR/hmi-screens
#   --work DIR   where the simulated cell is cached (default DIR/soak of the build folder)
# environment: CELLSIGHT_BIN  use this executable instead of building one
set -euo pipefail
cd "$(dirname "$0")/../.."

BUILD=build
WORK=
PASS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --build) BUILD=${2:?--build needs a folder}; shift ;;
    --work) WORK=${2:?--work needs a folder}; shift ;;
    -h|--help) awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit 0 ;;
    *) PASS+=("$1") ;;
  esac
  shift
done
WORK=${WORK:-$BUILD/soak}

missing=()
[ -x /usr/bin/chromium ] || missing+=("chromium (/usr/bin/chromium)")
command -v node >/dev/null || missing+=("node")
[ -f tests/browser/node_modules/puppeteer-core/package.json ] || missing+=("puppeteer-core (npm ci in tests/browser)")
if [ ${#missing[@]} -gt 0 ]; then
  echo "FAIL: the browser test cannot run: missing ${missing[*]}; scripts/setup.sh installs them" >&2
  exit 1
fi

if [ -z "${CELLSIGHT_BIN:-}" ]; then
  cmake -S . -B "$BUILD" -DCMAKE_BUILD_TYPE=Release >/dev/null
  cmake --build "$BUILD" -j"$(nproc)" --target cellsight
  CELLSIGHT_BIN=$BUILD/app/cellsight
fi
scripts/sim_cell.sh "$CELLSIGHT_BIN" "$WORK"
exec node tests/browser/hmi_browser.mjs --cellsight "$(realpath "$CELLSIGHT_BIN")" --cell "$WORK/cell" \
  --screens "$BUILD/hmi-screens" "${PASS[@]}"
