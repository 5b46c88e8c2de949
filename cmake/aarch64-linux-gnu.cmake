# Cross build for the ARM64 board: Debian's aarch64-linux-gnu-gcc 12 against the arm64 sysroot
# that scripts/arm64-sysroot makes (PULSETRACK_ARM64_SYSROOT, default
# ~/.cache/pulsetrack-arm64-sysroot). Host programs (idlc, pkg-config) come from the host;
# libraries, headers and CMake packages only from the sysroot. ctest runs the test programs under
# qemu-aarch64-static (CMAKE_CROSSCOMPILING_EMULATOR); QEMU_CPU picks the CPU it emulates
# (cortex-a72: NEON only; max, the default: SVE and SVE2 too).
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
if(DEFINED ENV{PULSETRACK_ARM64_SYSROOT})
  set(CMAKE_SYSROOT $ENV{PULSETRACK_ARM64_SYSROOT})
else()
  set(CMAKE_SYSROOT $ENV{HOME}/.cache/pulsetrack-arm64-sysroot)
endif()
if(NOT EXISTS ${CMAKE_SYSROOT}/usr/include/aarch64-linux-gnu)
  message(FATAL_ERROR "no arm64 sysroot at ${CMAKE_SYSROOT}: run scripts/arm64-sysroot")
endif()
set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)
set(CMAKE_FIND_ROOT_PATH ${CMAKE_SYSROOT})
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
set(ENV{PKG_CONFIG_SYSROOT_DIR} ${CMAKE_SYSROOT})
set(ENV{PKG_CONFIG_LIBDIR}
    ${CMAKE_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:${CMAKE_SYSROOT}/usr/share/pkgconfig)
set(CMAKE_CROSSCOMPILING_EMULATOR qemu-aarch64-static -L ${CMAKE_SYSROOT})
