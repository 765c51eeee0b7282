#!/usr/bin/env bash
# Two builds of the Python package, timed in alternating processes: a benchmark script that prints
# one JSON object of medians (e.g. bench/bench_threads.py --json) runs ROUNDS times per side, base
# and new in turn, and the median of each field per side is printed with new / base. For changes
# that two builds in one process cannot compare (bench/ab_builds.sh links both into one program):
# a thread pool, say, whose threads would spin beside the other side's.
#
#   bash bench/ab_python.sh BASE [NEW] SCRIPT [ARGS...]   # NEW: a revision, or "-" for the working tree
#   bash bench/ab_python.sh bfb696c - bench/bench_threads.py --json
#
# Environment: ROUNDS (default 3), PYTHON (default: the python on PATH, with numpy and the package's
# Python dependencies installed), BASE_ENV / NEW_ENV (variables for that side's processes, e.g.
# BASE_ENV=TERRACUBE_DISABLE_AVX2=1 runs 80f10ff without its AVX2 kernels). Each side's extension
# is built in a temporary folder (Release, no tests, benchmarks or PCL), about a minute per side on
# 2 cores.
set -euo pipefail

repo=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
base=${1:?usage: ab_python.sh BASE [NEW|-] SCRIPT [ARGS...]}
new=${2:?usage: ab_python.sh BASE [NEW|-] SCRIPT [ARGS...]}
shift 2
[ $# -ge 1 ] || { echo "ab_python.sh: no benchmark script given" >&2; exit 2; }
python=${PYTHON:-python}
rounds=${ROUNDS:-3}

work=$(mktemp -d)
cleanup() {
  git -C "$repo" worktree remove --force "$work/base" 2>/dev/null || true
  git -C "$repo" worktree remove --force "$work/new" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

pybind11_dir=$("$python" -c "import pybind11; print(pybind11.get_cmake_dir())")
build_side() {  # build_side SOURCE_TREE NAME: the package with its extension in $work/NAME_python
  cmake -S "$1" -B "$work/$2_build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DTERRACUBE_BUILD_PYTHON=ON \
    -DTERRACUBE_BUILD_TESTS=OFF -DTERRACUBE_BUILD_BENCH=OFF -DTERRACUBE_WITH_PCL=OFF \
    -DPython_EXECUTABLE="$(command -v "$python")" -Dpybind11_DIR="$pybind11_dir" >/dev/null
  cmake --build "$work/$2_build" --target _core >/dev/null
  cp -r "$1/python" "$work/$2_python"
  rm -f "$work/$2_python"/terracube/_core*.so
  cp "$work/$2_build"/bindings/_core*.so "$work/$2_python/terracube/"
}
git -C "$repo" worktree add -q --detach "$work/base" "$base"
build_side "$work/base" base
if [ "$new" = "-" ]; then
  build_side "$repo" new
else
  git -C "$repo" worktree add -q --detach "$work/new" "$new"
  build_side "$work/new" new
fi

# The script and its helpers come from the working tree, for both sides.
for round in $(seq "$rounds"); do
  for side in base new; do
    side_env=$([ "$side" = base ] && echo "${BASE_ENV:-}" || echo "${NEW_ENV:-}")
    # shellcheck disable=SC2086  # the side's variables, word-split on purpose
    echo "$side $(env $side_env PYTHONPATH="$work/${side}_python" "$python" "$@" | tail -n 1)" >>"$work/results"
  done
done
"$python" - "$work/results" "$base" "$new" <<'EOF'
import collections, json, os, statistics, sys

runs = collections.defaultdict(lambda: collections.defaultdict(list))
for line in open(sys.argv[1]):
    side, text = line.split(" ", 1)
    for name, value in json.loads(text).items():
        runs[name][side].append(value)
base, new = sys.argv[2], "working tree" if sys.argv[3] == "-" else sys.argv[3]
for name, variables in (("base", "BASE_ENV"), ("new", "NEW_ENV")):
    if os.environ.get(variables):
        print(f"{name} ran with {os.environ[variables]}")
rounds = max(len(sides["base"]) for sides in runs.values())
print(f"median per side of {rounds} alternating processes; base {base}, new {new}")
width = max(len(name) for name in runs)
print(f"{'':<{width}} {'base':>9} {'new':>9} {'new/base':>9}")
for name, sides in runs.items():  # a field one side does not print shows "-"
    b, n = (statistics.median(sides[s]) if sides[s] else None for s in ("base", "new"))
    text = [f"{v:9.3f}" if v is not None else f"{'-':>9}" for v in (b, n)]
    ratio = f"{n / b:9.3f}" if b and n is not None else f"{'-':>9}"
    print(f"{name:<{width}} {text[0]} {text[1]} {ratio}")
EOF
