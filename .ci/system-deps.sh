#!/usr/bin/env bash
# Install the system packages citytherm needs on Debian 12 (idempotent; needs root or sudo).
# - postgresql-15-postgis-3: PostGIS for the city model database (integration tests, service)
# - redis-server: Celery broker (integration tests, service)
# - libusb-1.0-0, libgomp1: shared libraries open3d-cpu loads at import
# - gdal-bin: ogrinfo reads the database as GIS clients do (tests/integration/test_db_srid.py)
# - docker-compose: validates docker-compose.yml (tests/unit/test_compose.py; no Docker engine needed)
# - chromium: headless browser of the /viewer test (tests/integration/test_viewer.py, via playwright-core)
# - nodejs, npm: the Khronos glTF validator (tools/gltf-validator, tests of the 3D Tiles export)
# - build-essential, python3-dev: C compiler and Python headers for the compiled CityGML walk that
#   `pip install` builds (setup.py, db/citygml/_walk.pyx; tests/unit/test_citygml_walk.py needs it)
set -euo pipefail
pkgs=(postgresql-15 postgresql-15-postgis-3 redis-server libusb-1.0-0 libgomp1 libgl1 libglib2.0-0 gdal-bin
      docker-compose chromium build-essential python3-dev)
# node + npm run the Khronos glTF validator (tests of the 3D Tiles export); a NodeSource nodejs
# bundles npm and conflicts with Debian's npm package, so only when npm is missing
command -v npm >/dev/null 2>&1 || pkgs+=(nodejs npm)
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "system-deps: all present"
  exit 0
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
echo "system-deps: installing ${missing[*]}"
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
