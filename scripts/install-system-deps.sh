#!/usr/bin/env bash
# Installs the Debian packages softphantom needs; idempotent (installs only what is missing).
#   gmsh wheel (headless): libglu1-mesa libgl1 libxcursor1 libxft2 libxinerama1 libgomp1
#   firmware build:        gcc-avr avr-libc binutils-avr
#   firmware in the loop:  simavr libsimavr-dev (the emulator library the harness firmware/sim links)
#   scikit-sparse (CHOLMOD, FEM solver): libsuitesparse-dev, and libopenblas0-pthread as the
#     system BLAS it factorizes with (3-7x faster than the reference BLAS it would otherwise get)
#   live page tests and benchmark (headless, driven by Playwright): chromium fonts-dejavu-core
set -euo pipefail
PKGS=(libglu1-mesa libgl1 libxcursor1 libxft2 libxinerama1 libgomp1
      gcc-avr avr-libc binutils-avr simavr libsimavr-dev
      chromium fonts-dejavu-core
      libsuitesparse-dev libopenblas0-pthread)
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "system packages: all present"
  exit 0
fi
echo "system packages: installing ${missing[*]}"
SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
