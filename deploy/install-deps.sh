#!/usr/bin/env bash
# Installs somasim's build and test dependencies from Debian's package registry.
# Idempotent: packages already present are skipped; nothing is downloaded from anywhere else.
# Usage: deploy/install-deps.sh            (as root, or with sudo available)
set -euo pipefail

PACKAGES=(
  # toolchain
  build-essential cmake ninja-build pkg-config git
  clang-14 libclang-rt-14-dev lld-14 clang-format clang-tidy
  # numerics
  libeigen3-dev libsuitesparse-dev libopenblas-dev
  # wire and data at rest
  cyclonedds-dev cyclonedds-tools libprotobuf-dev protobuf-compiler
  # mesh formats: XML (VTU) and zlib-compressed VTU blocks
  libpugixml-dev zlib1g-dev
  # viewer and its headless tests
  freeglut3-dev libgl-dev libglu1-mesa-dev libgl1-mesa-dri libpng-dev xvfb xauth
  # tests and benchmarks
  libgtest-dev libgmock-dev libbenchmark-dev libbullet-dev
  # an independent finite-element code the FEM is checked against (run as a program)
  calculix-ccx
  # application support
  libcli11-dev libspdlog-dev libfmt-dev nlohmann-json3-dev
  # external tetrahedraliser (AGPL: run as a program, never linked)
  tetgen
)

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#PACKAGES[@]} packages present"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "install-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
echo "install-deps: done"
