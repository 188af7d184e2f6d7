# Cross build for 64-bit ARM Linux (an ARM industrial PC or smart-camera board) from Debian 12 x86-64.
#
# With a sysroot (the way that works beside the native build; scripts/cross-build.sh aarch64 does all of it):
#   scripts/cross-build.sh aarch64      installs g++-aarch64-linux-gnu and qemu-user, builds the sysroot
#                                       build-aarch64/sysroot from Debian's arm64 packages (downloaded, unpacked
#                                       with dpkg -x, never installed), then configures and builds like this:
#   cmake -S . -B build-aarch64 -DCMAKE_TOOLCHAIN_FILE=toolchain/aarch64-linux-gnu.cmake \
#         -DCELLSIGHT_SYSROOT=$PWD/build-aarch64/sysroot -DCELLSIGHT_BUILD_TESTS=OFF
#   (or CELLSIGHT_SYSROOT in the environment). The compiler's C and C++ library headers and link files come from
#   the cross compiler's packages; the sysroot holds the libraries cellsight finds and loads.
#   Measured on the 2-core development machine: host tools 68 MB and 22 s once; the first run
#   downloads 9 MB of package lists and 73 MB of .deb files (164 packages, 288 MB unpacked) and takes 4 min 5 s on
#   an idle 2-core machine, 3.5 min of it compiling; a second run reuses the sysroot and the build: 4 s.
#   Run it without the hardware: qemu-aarch64 -L build-aarch64/sysroot build-aarch64/app/cellsight help
#   (scripts/cross-check.sh aarch64 compares its decisions and poses with the native binary's).
#
# Without CELLSIGHT_SYSROOT the arm64 -dev packages must be installed on the build machine as a foreign
# architecture (dpkg --add-architecture arm64 && apt-get update, then apt-get install libeigen3-dev
# libopencv-dev:arm64 libyaml-cpp-dev:arm64 libsvm-dev:arm64 libgpiod-dev:arm64 libmodbus-dev:arm64
# libsystemd-dev:arm64 zlib1g-dev:arm64). That suits only a machine or container kept for ARM builds: in Debian 12
# libopencv-dev is not Multi-Arch: same, so libopencv-dev:arm64 replaces the native one (apt's simulation on the
# development machine removes libopencv-dev and 29 more native packages) and the native build loses its OpenCV.
# This way is kept as it was and was not tried here for that reason.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)
# GCC notes on AArch64 that passing std::pair<double, double> changed in GCC 10.1: news for libraries built with an
# older GCC, not a finding here (all of Debian 12 and this build use GCC 12).
set(CMAKE_CXX_FLAGS_INIT -Wno-psabi)

if(NOT CELLSIGHT_SYSROOT AND DEFINED ENV{CELLSIGHT_SYSROOT})
  set(CELLSIGHT_SYSROOT "$ENV{CELLSIGHT_SYSROOT}")
endif()
# try_compile projects read this file again: hand them the sysroot too.
list(APPEND CMAKE_TRY_COMPILE_PLATFORM_VARIABLES CELLSIGHT_SYSROOT)

if(CELLSIGHT_SYSROOT)
  if(NOT EXISTS "${CELLSIGHT_SYSROOT}/usr/lib/aarch64-linux-gnu")
    message(FATAL_ERROR "CELLSIGHT_SYSROOT=${CELLSIGHT_SYSROOT} holds no arm64 libraries: "
                        "run scripts/cross-build.sh aarch64")
  endif()
  set(CMAKE_SYSROOT "${CELLSIGHT_SYSROOT}")
  set(CMAKE_FIND_ROOT_PATH "${CELLSIGHT_SYSROOT}")
  set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
  set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
  set(ENV{PKG_CONFIG_SYSROOT_DIR} "${CELLSIGHT_SYSROOT}")
  set(ENV{PKG_CONFIG_LIBDIR}
      "${CELLSIGHT_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:${CELLSIGHT_SYSROOT}/usr/share/pkgconfig")
else()
  set(CMAKE_FIND_ROOT_PATH /usr/aarch64-linux-gnu /usr/lib/aarch64-linux-gnu)
  set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE BOTH)
  set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE BOTH)
  set(ENV{PKG_CONFIG_LIBDIR} /usr/lib/aarch64-linux-gnu/pkgconfig:/usr/share/pkgconfig)
endif()
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
