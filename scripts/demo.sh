#!/usr/bin/env bash
# README command 1: set everything up, then remove the overhangs from the bundled sample scan
# and write the classified cloud and a picture to terracube_demo/.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
bash scripts/setup.sh
.venv/bin/terracube demo --output-dir terracube_demo
