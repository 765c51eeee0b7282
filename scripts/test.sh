#!/usr/bin/env bash
# README command 2: set everything up, then build the C++ core alone and run every test:
# ctest (GoogleTest + the find_package consumer) and pytest.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
bash scripts/setup.sh

generator=()
if command -v ninja >/dev/null; then generator=(-G Ninja); fi
cmake -S . -B build "${generator[@]}" -DCMAKE_BUILD_TYPE=Release -DTERRACUBE_BUILD_TESTS=ON
cmake --build build --parallel 2
ctest --test-dir build --output-on-failure --parallel 2
.venv/bin/python -m pytest -q tests/python
