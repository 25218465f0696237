#!/usr/bin/env bash
# Set up everything aimbench needs on a fresh Debian 12 machine with Python >= 3.11:
# the Debian packages (as root, with apt-get), then .venv with the project and the extras named.
# Idempotent: packages already installed are not fetched again.
#
#   tools/setup.sh              the main job only (what `make demo` needs)
#   tools/setup.sh test,bench   with the extras of pyproject.toml named (`make test`, `make bench`)
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS=${1:-}
case "$EXTRAS" in
  *[!a-z0-9,-]*) echo "setup: error: extras are names separated by commas (e.g. test,bench), got '$EXTRAS'" >&2; exit 1 ;;
esac

# Why each Debian package:
#   libusb-1.0-0                       open3d's Python module links against it
#   gcc-avr avr-libc arduino-core-avr  build the Arduino Mega firmware (bench_fw/)
#   libsimavr-dev libelf-dev pkg-config  build the simavr hardware-in-the-loop harness
#   make g++                           the firmware's host-side unit tests and the harness
#   libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0
#                                      MuJoCo's offscreen rendering without a display (EGL with
#                                      Mesa's software rasteriser): `aimbench render`, the gym
#                                      env's render_mode="rgb_array"
DEBS=(libusb-1.0-0 gcc-avr avr-libc arduino-core-avr libsimavr-dev libelf-dev pkg-config make g++
      libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0)

# Only for the tests (the extra `test`: `tools/setup.sh test`, which `make test` runs):
#   chromium chromium-driver           a real headless browser for the line station's pages
#                                      (tests/test_line_station.py, Selenium with
#                                      /usr/bin/chromedriver: no browser is downloaded)
TEST_DEBS=(chromium chromium-driver)
case ",$EXTRAS," in
  *,test,*) DEBS+=("${TEST_DEBS[@]}") ;;
esac

PYTHON=${PYTHON:-}
if [ -z "$PYTHON" ]; then
  for candidate in python3.11 python3.12 python3.13 python3; do
    if command -v "$candidate" >/dev/null 2>&1 &&
       "$candidate" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
      PYTHON=$candidate; break
    fi
  done
fi
[ -n "$PYTHON" ] || { echo "setup: error: need Python >= 3.11 on PATH (or set PYTHON=...)" >&2; exit 1; }
# Debian's own Python needs python3-venv for `-m venv`.
"$PYTHON" -c 'import ensurepip, venv' 2>/dev/null || DEBS+=(python3-venv)

missing=()
for pkg in "${DEBS[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -eq 0 ]; then
    echo "setup: installing Debian packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    echo "setup: error: missing Debian packages: ${missing[*]}; run as root or: sudo apt-get install ${missing[*]}" >&2
    exit 1
  fi
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $PYTHON"
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
if [ -n "$EXTRAS" ]; then
  echo "setup: installing aimbench with the extras $EXTRAS into .venv"
  .venv/bin/python -m pip install -q -e ".[$EXTRAS]"
else
  echo "setup: installing aimbench (the main job's libraries only) into .venv"
  .venv/bin/python -m pip install -q -e .
fi
# ouster-sdk (the extra `ouster`, and `test`, whose tests run it): installed without its
# dependencies, since every release 0.14-1.0.1 pins rosbags==0.9.23, flask==3.0, click<8.1.8 and
# psutil<6 (1.0.1's METADATA) and pip would downgrade the project's rosbags>=0.11 to them. What
# its core, pcap and osf modules import came with the extra above (pyproject.toml).
case ",$EXTRAS," in
  *,ouster,*|*,test,*)
    echo "setup: installing ouster-sdk 1.0.1 without its pinned dependencies"
    .venv/bin/python -m pip install -q --no-deps "ouster-sdk==1.0.1" ;;
esac
# Compile the numba kernels now, into numba's cache (beside their modules), so the first command
# of a fresh install does not wait for them (scenarios/warmup.py).
echo "setup: compiling the numba kernels (once: about 3.5 minutes of one core; benchmarks/bench_warmup.py)"
.venv/bin/python -m scenarios.warmup
