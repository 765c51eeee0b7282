#!/usr/bin/env bash
# Regenerates python/terracube/_core/*.pyi, the type stubs of the compiled module, from the build in
# .venv (run scripts/setup.sh after changing bindings/ first). tests/python/test_docs.py fails when
# the committed stubs and _core disagree.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
.venv/bin/pybind11-stubgen terracube._core --numpy-array-use-type-var -o "$out"
rm -rf python/terracube/_core
mkdir -p python/terracube/_core
cp "$out"/terracube/_core/*.pyi python/terracube/_core/   # a package: _core has a simulation submodule
echo "written: python/terracube/_core/"
