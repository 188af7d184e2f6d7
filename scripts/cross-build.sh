#!/usr/bin/env bash
# Cross build of cellsight for an ARM Linux target (issue 16), beside the native build and without touching it.
#   1. host tools: the cross compiler and qemu-user from Debian (scripts/setup.sh PACKAGE...: apt-get, idempotent);
#   2. sysroot: the target's Debian packages are resolved and downloaded by a private apt (its own architecture,
#      lists, cache and an empty package status under build-TARGET/apt; the host's dpkg database, foreign
#      architectures and -dev packages stay as they were) and unpacked with dpkg -x into build-TARGET/sysroot;
#   3. configure with toolchain/TRIPLET.cmake and CELLSIGHT_SYSROOT, build the cellsight executable
#      (build-TARGET/app/cellsight; tests off);
#   4. checks: the file is an ELF of the target, every shared library it needs (recursively) is in the sysroot,
#      and `cellsight help` runs under qemu-user with the sysroot as its library root.
# A complete sysroot is reused: a second run only rebuilds what changed. The sysroot is rebuilt when the package
# lists below change (they are hashed into build-TARGET/sysroot/.cellsight-sysroot); delete build-TARGET to start over.
# The proof against the native binary is scripts/cross-check.sh TARGET.
#
# usage: scripts/cross-build.sh TARGET        (TARGET: aarch64)
# environment: CELLSIGHT_DEBIAN_MIRROR    Debian archive (default http://deb.debian.org/debian)
#              CELLSIGHT_DEBIAN_SECURITY  Debian security archive (default http://deb.debian.org/debian-security)
set -euo pipefail
cd "$(dirname "$0")/.."

[ $# -eq 1 ] || { echo "usage: scripts/cross-build.sh TARGET   (TARGET: aarch64)" >&2; exit 2; }
TARGET=$1
case "$TARGET" in
  aarch64)
    DEB_ARCH=arm64
    TRIPLET=aarch64-linux-gnu
    QEMU=qemu-aarch64
    ELF_MACHINE=AArch64  # what readelf -h prints as Machine
    ;;
  *) echo "cross-build.sh: unknown target '$TARGET' (known: aarch64)" >&2; exit 2 ;;
esac

BUILD=build-$TARGET
SYSROOT=$BUILD/sysroot
APT_DIR=$PWD/$BUILD/apt  # absolute: apt runs from its download folder
TOOLCHAIN=toolchain/$TRIPLET.cmake
HOST_PACKAGES=(cmake pkg-config file "g++-$TRIPLET" "binutils-$TRIPLET" qemu-user)

# What the sysroot holds. The compiler, the C library's and the C++ library's headers and link files come from the
# cross compiler's own packages (libc6-dev-arm64-cross, libstdc++-12-dev-arm64-cross: the same glibc 2.36 and GCC 12.2
# sources as the target's libc6 and libstdc++6), so the sysroot needs none of them.
#   DEV_PACKAGES      headers, lib*.so links, pkg-config and CMake files of what CMakeLists.txt finds; unpacked
#                     without their dependencies (libopencv-dev alone ships OpenCVConfig.cmake and would pull in
#                     every OpenCV module; the -dev packages of the five modules cellsight links and flann, which
#                     features2d and calib3d link, are enough)
#   RUNTIME_PACKAGES  the libraries the executable loads; unpacked with everything they depend on (Depends and
#                     Pre-Depends, not Recommends), so that linking and running under qemu find every library
#   NOT_NEEDED        packages in that dependency closure that cellsight never loads, left out: libglx-mesa0 is the
#                     OpenGL driver that libglvnd's libGLX loads only when a GL context is created (with it come
#                     Mesa's DRI drivers and LLVM, 35 MB); proj-data is PROJ's datum grids for GDAL's reprojection
DEV_PACKAGES=(
  libeigen3-dev
  libopencv-dev libopencv-core-dev libopencv-imgproc-dev libopencv-imgcodecs-dev libopencv-calib3d-dev
  libopencv-features2d-dev libopencv-flann-dev
  libyaml-cpp-dev libsvm-dev libgpiod-dev libmodbus-dev libsystemd-dev zlib1g-dev
  libcivetweb-dev nlohmann-json3-dev libcrypt-dev
)
RUNTIME_PACKAGES=(
  libc6 libgcc-s1 libstdc++6
  libopencv-core406 libopencv-imgproc406 libopencv-imgcodecs406 libopencv-calib3d406 libopencv-features2d406
  libopencv-flann406
  libyaml-cpp0.7 libsvm3 libgpiod2 libmodbus5 libsystemd0 zlib1g
  libcivetweb1 libcrypt1
)
NOT_NEEDED=(libglx-mesa0 proj-data)

START=$SECONDS
step() { echo "== $1 [at $((SECONDS - START)) s]"; }
die() { echo "cross-build.sh: $*" >&2; exit 1; }

# --- 1. host tools ----------------------------------------------------------------------------------------------
step "1. host tools: ${HOST_PACKAGES[*]}"
scripts/setup.sh "${HOST_PACKAGES[@]}"

# --- 2. sysroot ---------------------------------------------------------------------------------------------------
# shellcheck source=/dev/null  # the host's release: the sysroot's packages come from the same Debian suite
. /etc/os-release
SUITE=${VERSION_CODENAME:?no VERSION_CODENAME in /etc/os-release}
RECIPE="$SUITE $DEB_ARCH dev: ${DEV_PACKAGES[*]} runtime: ${RUNTIME_PACKAGES[*]} not needed: ${NOT_NEEDED[*]}"
RECIPE_HASH=$(printf '%s\n' "$RECIPE" | sha256sum | cut -c1-16)
STAMP=$SYSROOT/.cellsight-sysroot

# write_apt_config: the private apt's configuration and Debian sources under $APT_DIR.
write_apt_config() {
  local dir=$APT_DIR
  mkdir -p "$dir/lists/partial" "$dir/archives/partial" "$dir/sources.list.d"
  cat >"$dir/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: ${CELLSIGHT_DEBIAN_MIRROR:-http://deb.debian.org/debian}
Suites: $SUITE $SUITE-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: ${CELLSIGHT_DEBIAN_SECURITY:-http://deb.debian.org/debian-security}
Suites: $SUITE-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
  cat >"$dir/apt.conf" <<EOF
// Private apt of scripts/cross-build.sh: $DEB_ARCH packages only, its own lists, cache and package status.
APT::Architecture "$DEB_ARCH";
APT::Architectures { "$DEB_ARCH"; };
Dir::State "$dir";
Dir::State::Lists "$dir/lists";
Dir::State::status "$dir/status";
Dir::Cache "$dir";
Dir::Cache::archives "$dir/archives";
Dir::Etc::SourceList "/dev/null";
Dir::Etc::SourceParts "$dir/sources.list.d";
Debug::NoLocking "true";
APT::Sandbox::User "root";
EOF
}
# apt_arch TOOL ARGS...: apt-get or apt-cache for the target architecture, on the private state under $APT_DIR.
apt_arch() {
  local tool=$1
  shift
  APT_CONFIG=$APT_DIR/apt.conf "$tool" -q "$@"
}

# fake_status: a dpkg status that marks NOT_NEEDED as installed, so the resolver neither fetches them nor what
# only they depend on. Everything else counts as absent: the closure includes libc6 and the rest of the base.
fake_status() {
  local p
  for p in "${NOT_NEEDED[@]}"; do
    apt_arch apt-cache show --no-all-versions "$p" | awk '/^(Package|Version|Architecture|Multi-Arch):/'
    echo "Status: install ok installed"
    echo
  done
}

# fix_links DIR: absolute symlinks (e.g. libz.so -> /lib/TRIPLET/libz.so.1.2.13) would point into the host; make
# them relative, inside the sysroot.
fix_links() {
  local root=$1 link target
  while IFS= read -r -d '' link; do
    target=$(readlink "$link")
    [[ $target == /* ]] || continue
    ln -sfn "$(realpath -m --relative-to="$(dirname "$link")" "$root$target")" "$link"
  done < <(find "$root" -type l -print0)
}

build_sysroot() {
  step "2. sysroot: resolving $DEB_ARCH packages of Debian $SUITE (private apt in $APT_DIR)"
  write_apt_config
  : >"$APT_DIR/status"
  apt_arch apt-get update >"$APT_DIR/update.log" 2>&1 || { cat "$APT_DIR/update.log" >&2; die "apt-get update failed"; }
  fake_status >"$APT_DIR/status"
  local runtime=()
  mapfile -t runtime < <(apt_arch apt-get install -s --no-install-recommends "${RUNTIME_PACKAGES[@]}" |
    awk '/^Inst /{print $2}')
  [ ${#runtime[@]} -gt 0 ] || die "could not resolve ${RUNTIME_PACKAGES[*]}"
  mapfile -t packages < <(printf '%s\n' "${runtime[@]}" "${DEV_PACKAGES[@]}" | sort -u)

  # 'URI' FILE SIZE HASH per package: the exact file names to unpack
  apt_arch apt-get download --print-uris "${packages[@]}" >"$APT_DIR/uris.txt"
  step "   downloading ${#packages[@]} packages into $APT_DIR/archives"
  (cd "$APT_DIR/archives" && apt_arch apt-get download "${packages[@]}" >/dev/null) || die "apt-get download failed"

  step "   unpacking into $SYSROOT"
  local tmp=$SYSROOT.partial deb
  rm -rf "$tmp" "$SYSROOT"
  mkdir -p "$tmp"
  while read -r _ deb _; do
    dpkg-deb -x "$APT_DIR/archives/$deb" "$tmp"
  done <"$APT_DIR/uris.txt"
  fix_links "$tmp"
  # update-alternatives would link the reference BLAS and LAPACK into the library folder; dpkg -x runs no scripts.
  local lib
  for lib in "$tmp"/usr/lib/"$TRIPLET"/{blas,lapack}/lib*.so.*; do
    [ -e "$lib" ] && [ ! -e "$tmp/usr/lib/$TRIPLET/$(basename "$lib")" ] &&
      ln -s "$(basename "$(dirname "$lib")")/$(basename "$lib")" "$tmp/usr/lib/$TRIPLET/$(basename "$lib")"
  done
  # OpenCVModules.cmake refuses to load unless every module's library exists; only the linked ones are here, so the
  # file-existence check of the others is taken out of the sysroot's copy (their targets stay defined, unused).
  local modules=$tmp/usr/lib/$TRIPLET/cmake/opencv4/OpenCVModules-release.cmake module
  [ -f "$modules" ] || die "no $modules in libopencv-dev"
  while read -r module; do
    if ! ls "$tmp/usr/lib/$TRIPLET/lib$module.so."* >/dev/null 2>&1; then
      sed -i "/^list(APPEND _cmake_import_check_targets $module )\$/d;
              /^list(APPEND _cmake_import_check_files_for_$module /d" "$modules"
    fi
  done < <(sed -n 's/^list(APPEND _cmake_import_check_targets \(opencv_[a-z0-9_]*\) )$/\1/p' "$modules")
  echo "$RECIPE_HASH $RECIPE" >"$tmp/.cellsight-sysroot"
  mv "$tmp" "$SYSROOT"
  local deb_mb
  deb_mb=$(awk '{s += $3} END {printf "%.1f", s / 1e6}' "$APT_DIR/uris.txt")
  echo "   sysroot: ${#packages[@]} packages, $deb_mb MB of .deb files, $(du -sm "$SYSROOT" | cut -f1) MB unpacked"
}

if [ -f "$STAMP" ] && [ "$(cut -d' ' -f1 "$STAMP")" = "$RECIPE_HASH" ]; then
  step "2. sysroot $SYSROOT reused ($(du -sm "$SYSROOT" | cut -f1) MB)"
else
  build_sysroot
fi

# --- 3. configure and build -------------------------------------------------------------------------------------
step "3. configuring $BUILD ($TOOLCHAIN, Release, tests off)"
cmake -S . -B "$BUILD" -DCMAKE_TOOLCHAIN_FILE="$TOOLCHAIN" -DCELLSIGHT_SYSROOT="$(realpath "$SYSROOT")" \
  -DCMAKE_BUILD_TYPE=Release -DCELLSIGHT_BUILD_TESTS=OFF >"$BUILD/configure.log" 2>&1 ||
  { cat "$BUILD/configure.log" >&2; die "configure failed (log: $BUILD/configure.log)"; }
step "   building cellsight"
cmake --build "$BUILD" -j"$(nproc)" --target cellsight
BIN=$BUILD/app/cellsight

# --- 4. checks ----------------------------------------------------------------------------------------------------
step "4. checking $BIN"
file "$BIN"
machine=$("$TRIPLET-readelf" -h "$BIN" | awk -F: '/Machine:/{gsub(/^ +/, "", $2); print $2}')
[ "$machine" = "$ELF_MACHINE" ] || die "$BIN is built for '$machine', not $ELF_MACHINE"
# Every DT_NEEDED, recursively, must be in the sysroot's library folders: what a linker could miss (it only warns
# about libraries of libraries) and what qemu or the target would fail to load.
lib_dirs=("$SYSROOT/lib/$TRIPLET" "$SYSROOT/usr/lib/$TRIPLET" "$SYSROOT/lib" "$SYSROOT/usr/lib")
declare -A seen=()
queue=("$BIN")
unresolved=()
while [ ${#queue[@]} -gt 0 ]; do
  elf=${queue[0]}
  queue=("${queue[@]:1}")
  for soname in $("$TRIPLET-readelf" -d "$elf" | sed -n 's/.*(NEEDED).*\[\(.*\)\]/\1/p'); do
    [ -z "${seen[$soname]:-}" ] || continue
    seen[$soname]=1
    found=
    for d in "${lib_dirs[@]}"; do
      if [ -e "$d/$soname" ]; then found=$d/$soname; break; fi
    done
    if [ -n "$found" ]; then queue+=("$found"); else unresolved+=("$soname (needed by ${elf#"$SYSROOT"/})"); fi
  done
done
[ ${#unresolved[@]} -eq 0 ] || die "libraries missing from the sysroot: ${unresolved[*]}"
echo "   ${#seen[@]} shared libraries needed, all in the sysroot"
"$QEMU" -L "$SYSROOT" "$BIN" help >/dev/null || die "'$QEMU -L $SYSROOT $BIN help' failed"
echo "   $QEMU -L $SYSROOT $BIN help: exit 0"
step "done: $BIN"
