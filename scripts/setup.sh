#!/usr/bin/env bash
# Set up everything the workbench needs on a fresh Debian 12 machine (run as root). Idempotent and quick
# the second time: installs only what is missing.
#  - Debian packages: headless rendering (Open3D 0.20 renders through Vulkan; Mesa's lavapipe driver
#    provides it on the CPU), Xvfb for the desktop windows, Pango for the PDF report (WeasyPrint),
#    poppler-utils to look at PDF pages, and the clients the export tests check the files with: GDAL's
#    ogrinfo, Blender, Node.js with the Khronos glTF validator (npm package gltf-validator); Chromium, which
#    the picker test drives (through Playwright);
#  - uv, a virtual environment in .venv, and the package with the locked dependency versions (uv.lock).
# `scripts/setup.sh --demo` installs only what a run needs (rendering and the PDF report: scripts/demo.sh uses
# it); the clients the tests check the exports with (GDAL, Blender, Node.js, Chromium, Xvfb) come with the plain
# `scripts/setup.sh` (scripts/test.sh). `scripts/setup.sh --bench` also installs Hugin (hugin-tools, enblend) for
# scripts/bench_stitch.py.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libusb-1.0-0 libvulkan1 mesa-vulkan-drivers libegl1 libgl1 libgomp1 libpango-1.0-0 libpangoft2-1.0-0)
PROFILE=${1:-}
if [ "$PROFILE" != "--demo" ]; then
  APT_PACKAGES+=(xvfb xauth poppler-utils gdal-bin blender chromium)
  command -v npm >/dev/null 2>&1 || APT_PACKAGES+=(nodejs npm)
fi
if [ "$PROFILE" = "--bench" ]; then APT_PACKAGES+=(hugin-tools enblend); fi
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; else SUDO=; fi
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# the Khronos glTF validator (a library; the tests call it through node)
if [ "$PROFILE" != "--demo" ] && [ ! -d "$(npm root -g 2>/dev/null)/gltf-validator" ]; then
  echo "setup: installing the Khronos glTF validator (npm gltf-validator)"
  $SUDO npm install -g --silent --no-fund --no-audit gltf-validator >/dev/null 2>&1 \
    || echo "setup: could not install gltf-validator from npm; the glTF validator test will be skipped"
fi

if ! command -v uv >/dev/null 2>&1; then
  echo "setup: installing uv"
  python3 -m pip install --quiet --disable-pip-version-check uv
fi
# --locked: fail rather than silently change versions if uv.lock and pyproject.toml disagree.
# --compile-bytecode (and compileall for the package): Python then starts from .pyc files even where the
# environment sets PYTHONDONTWRITEBYTECODE (as this machine's does): without them every command compiled every
# module it imported from source (1.5 s of the render stage's 20 s; `workbench types` 0.87 -> 0.6 s).
uv sync --quiet --locked --extra test --python 3.11 --compile-bytecode
.venv/bin/python -m compileall -q workbench >/dev/null
