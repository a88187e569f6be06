#!/usr/bin/env bash
# Installs the system packages skelid needs on a fresh Debian 12 machine:
#   libhdf5-dev + pkg-config  -> the HDF5 binding (hdf5-metno) links against Debian's libhdf5
#   libvulkan1 + mesa-vulkan-drivers -> wgpu's Vulkan backend; lavapipe is the software GPU CI tests on
#   vulkan-tools              -> `vulkaninfo --summary` for diagnosing adapters
#   chromium                  -> the headless browser the report test opens report.html in
#   poppler-utils             -> pdftoppm/pdftotext, with which the figures test renders --figures pdf
#   python3 + python3-venv    -> the Python package (pip install ./python) and its tests
#   slurm-wlm + munge         -> the job-array recipe's test runs a single-node Slurm (scripts/slurm)
# Safe to run repeatedly. Uses sudo only when not already root.
set -euo pipefail
pkgs=(libhdf5-dev pkg-config libvulkan1 mesa-vulkan-drivers vulkan-tools chromium poppler-utils python3 python3-venv slurm-wlm munge)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all system packages present (${pkgs[*]})"
else
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "install-deps: installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
command -v cargo >/dev/null || { echo "install-deps: cargo not found; install Rust (rustup) first" >&2; exit 1; }
