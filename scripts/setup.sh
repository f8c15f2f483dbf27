#!/usr/bin/env bash
# Set up everything the workbench needs on a fresh Debian 12 machine (run as root). Idempotent and quick
# the second time: installs only what is missing.
#  - Debian packages for headless rendering (Open3D 0.20 renders through Vulkan; Mesa's lavapipe driver
#    provides it on the CPU), Xvfb for the desktop windows, poppler-utils to look at PDF reports;
#  - uv, a virtual environment in .venv, and the package with the locked dependency versions (uv.lock).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1 xvfb xauth poppler-utils)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; else SUDO=; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! command -v uv >/dev/null 2>&1; then
  echo "setup: installing uv"
  python3 -m pip install --quiet --disable-pip-version-check uv
fi
# --locked: fail rather than silently change versions if uv.lock and pyproject.toml disagree
uv sync --quiet --locked --extra test --python 3.11
