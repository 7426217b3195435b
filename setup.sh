#!/usr/bin/env bash
# Set Persona up on a fresh Debian/Ubuntu machine and run it.
#
#   bash setup.sh demo    # install, then run the embedded demo end to end (synthetic faces)
#   bash setup.sh test    # install, then run the test suite
#   bash setup.sh         # install only
#
# Installs: the system packages open3d needs (libusb-1.0-0, libgomp1; for `test` also
# chromium, in which the tests open the reports, and npm when it is missing), a virtual
# environment in .venv with Persona (editable) and its Python dependencies. For `test` it also
# installs the Khronos glTF validator (npm's gltf-validator, into .venv/node), which checks the
# .glb exports, and starts a single-node SLURM (.ci/slurm-up.sh: Debian's slurm-wlm and munge);
# when that fails, the tests that need it skip.
set -euo pipefail
cd "$(dirname "$0")"

PYTHON=${PYTHON:-python3}
"$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))' || {
  echo "Persona needs Python 3.11 or newer; set PYTHON=/path/to/python3.11" >&2; exit 1; }

packages=(libusb-1.0-0 libgomp1)
if [ "${1:-}" = test ]; then
  packages+=(chromium)                        # the reports' tests open them in a real browser
  command -v npm >/dev/null || packages+=(npm)  # installs the glTF validator below
fi
missing=()
for pkg in "${packages[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
"$PYTHON" -c 'import venv, ensurepip' 2>/dev/null || missing+=("python3-venv")
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "installing system packages: ${missing[*]}"
  apt_get() {  # apt-get, waiting (up to 10 minutes) while another apt or dpkg holds its lock
    local out
    for _ in $(seq 120); do
      if out=$($SUDO env DEBIAN_FRONTEND=noninteractive apt-get "$@" 2>&1); then return 0; fi
      grep -q "Could not get lock" <<<"$out" || { echo "$out" >&2; return 1; }
      echo "apt-get $1: another apt-get or dpkg holds its lock; waiting" >&2; sleep 5
    done
    echo "$out" >&2; return 1
  }
  apt_get update -qq
  apt_get install -y -qq "${missing[@]}"
fi

[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q -e ".[test]"

if [ "${1:-}" = test ]; then  # the Khronos glTF validator for the .glb tests (tests/gltf_check.py)
  SECONDS=0
  [ -d .venv/node/node_modules/gltf-validator ] ||
    npm install --prefix .venv/node --no-audit --no-fund --silent gltf-validator@2.0.0-dev.3.10 ||
    echo "gltf-validator not installed ($SECONDS s): the .glb validation tests will skip"
fi

if [ "${1:-}" = test ]; then  # a single-node SLURM for the batch-cluster tests; they skip without it
  SECONDS=0
  bash .ci/slurm-up.sh || echo "SLURM not started ($SECONDS s): the tests of cluster.kind slurm will skip"
fi

case "${1:-}" in
  demo) shift; exec .venv/bin/persona demo "$@" ;;
  test) shift; exec .venv/bin/python -m pytest "$@" ;;
  "")   echo "installed: run .venv/bin/persona --help" ;;
  *)    echo "usage: bash setup.sh [demo|test] [args...]" >&2; exit 2 ;;
esac
