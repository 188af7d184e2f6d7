#!/usr/bin/env bash
# Installs every Debian 12 package cellsight needs to build, test and run. Idempotent and non-interactive:
# packages already present are not touched; apt-get runs only when something is missing.
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
)
if [ $# -gt 0 ]; then PACKAGES=("$@"); fi

SUDO=()
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "setup.sh: not root and no sudo; run as root" >&2; exit 1; }
  SUDO=(sudo)
fi

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "setup.sh: all ${#PACKAGES[@]} packages present"
  exit 0
fi

echo "setup.sh: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
"${SUDO[@]}" apt-get update -q
"${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
