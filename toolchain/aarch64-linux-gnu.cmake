# Cross build for 64-bit ARM Linux (e.g. an ARM industrial PC) from Debian 12 x86-64.
# Needs: apt-get install g++-aarch64-linux-gnu, and the arm64 -dev libraries:
#   dpkg --add-architecture arm64 && apt-get update
#   apt-get install libeigen3-dev libopencv-dev:arm64 libyaml-cpp-dev:arm64 libsvm-dev:arm64 \
#                   libgpiod-dev:arm64 libmodbus-dev:arm64 libsystemd-dev:arm64 catch2
#   cmake -S . -B build-arm64 -DCMAKE_TOOLCHAIN_FILE=toolchain/aarch64-linux-gnu.cmake -DCELLSIGHT_BUILD_TESTS=OFF
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)
set(CMAKE_FIND_ROOT_PATH /usr/aarch64-linux-gnu /usr/lib/aarch64-linux-gnu)
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE BOTH)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE BOTH)
set(ENV{PKG_CONFIG_LIBDIR} /usr/lib/aarch64-linux-gnu/pkgconfig:/usr/share/pkgconfig)
