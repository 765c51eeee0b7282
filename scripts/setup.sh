#!/usr/bin/env bash
# Sets up everything terracube needs on Debian 12, idempotently:
#   1. Debian's -dev packages and python3-rosbag (apt-get update first, noninteractive; skipped
#      when all are present),
#   2. a virtual environment .venv with terracube and its test tools installed by pip.
# Environment: PYTHON (default python3) picks the interpreter for .venv.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

packages=(
  build-essential cmake ninja-build pkg-config git
  libeigen3-dev libtbb-dev libpcl-dev liboctomap-dev libceres-dev libgtest-dev libbenchmark-dev pybind11-dev
  python3-dev python3-venv python3-pip
  python3-rosbag  # ROS 1's reference bag reader: tests check the ROS 1 bags we write with it
)
missing=()
for package in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing+=("$package")
done
if ((${#missing[@]})); then
  sudo=""
  if [[ $(id -u) -ne 0 ]]; then sudo="sudo"; fi
  echo "setup: installing Debian packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  echo "setup: Debian packages already installed"
fi

python="${PYTHON:-python3}"
if [[ ! -x .venv/bin/python ]]; then
  echo "setup: creating .venv with $python"
  "$python" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
echo "setup: building and installing terracube into .venv (C++ extension, takes a minute)"
.venv/bin/python -m pip install -q ".[test]"
.venv/bin/terracube version >/dev/null
echo "setup: done"
