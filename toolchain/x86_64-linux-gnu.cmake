# Native x86-64 Linux build (the development machine and most industrial PCs). Portable: no -march=native,
# so the binary runs on any x86-64 CPU; configure with -DCELLSIGHT_NATIVE=ON to tune for the build machine.
#   cmake -S . -B build -DCMAKE_TOOLCHAIN_FILE=toolchain/x86_64-linux-gnu.cmake
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR x86_64)
set(CMAKE_C_COMPILER gcc)
set(CMAKE_CXX_COMPILER g++)
