#!/usr/bin/env bash
# Installs every Debian 12 package cellsight needs to build, test and run. Idempotent and non-interactive:
# packages already present are not touched; apt-get runs only when something is missing.
# With no arguments it also installs the browser test's npm packages (tests/browser/: `npm ci` from the committed
# package-lock.json, puppeteer-core, which drives Debian's chromium and downloads no browser of its own); again only
# when the lock file changed since the last install.
# usage: scripts/setup.sh [PACKAGE...]   the packages named instead (scripts/cross-build.sh: the cross compiler)
set -euo pipefail

PACKAGES=(
  build-essential cmake pkg-config git
  libeigen3-dev libopencv-dev libyaml-cpp-dev libsvm-dev
  libgpiod-dev libmodbus-dev libsystemd-dev zlib1g-dev
  libcivetweb-dev nlohmann-json3-dev libcrypt-dev   # the operator's screen: HTTP server, JSON, password hashes
  catch2
  clang libclang-rt-14-dev   # libFuzzer and the sanitizer runtimes for the fuzz targets (scripts/fuzz.sh)
  clang-format clang-tidy    # the code rules (scripts/lint.sh, a stage of scripts/test.sh)
  mbpoll python3 python3-pymodbus python3-serial-asyncio   # real Modbus clients for the PLC tests
  chromium nodejs            # the operator's screen tested in a real browser (tests/browser/, puppeteer-core)
)
NPM_DIRS=("$(cd "$(dirname "$0")/.." && pwd)/tests/browser")
if [ $# -gt 0 ]; then PACKAGES=("$@"); NPM_DIRS=(); fi

SUDO=()
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "setup.sh: not root and no sudo; run as root" >&2; exit 1; }
  SUDO=(sudo)
fi

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
# Debian's nodejs comes without npm (its own package); NodeSource's nodejs brings npm along and conflicts with it.
if [ ${#NPM_DIRS[@]} -gt 0 ] && ! command -v npm >/dev/null; then missing+=(npm); fi

if [ ${#missing[@]} -eq 0 ]; then
  echo "setup.sh: all ${#PACKAGES[@]} packages present"
else
  echo "setup.sh: installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  "${SUDO[@]}" apt-get update -q
  "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

for dir in "${NPM_DIRS[@]}"; do
  stamp=$dir/node_modules/.cellsight-lock-sha256
  want=$(sha256sum "$dir/package-lock.json" | cut -d' ' -f1)
  if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "setup.sh: npm ci in $dir"
    (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error)
    echo "$want" > "$stamp"
  fi
done
