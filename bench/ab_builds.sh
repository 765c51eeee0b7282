#!/usr/bin/env bash
# Paired before/after timing of the elevation map path (build_elevation_map + classify_terrain on
# KITTI 00/000000 into the 400 x 200 map of bench_elevation.py) for two git revisions, in one
# process: see bench/cpp/ab_maps.cpp. On this shared VM the speed drifts by tens of percent within
# seconds, so two runs of two binaries cannot resolve a few percent; paired rounds in one process can.
#
#   bash bench/ab_builds.sh BASE [NEW]        # NEW defaults to the working tree
#   bash bench/ab_builds.sh HEAD HEAD         # A/A: what code placement alone does (read this first)
#
# Environment: THREADS (default "1 2"), WHAT (0 refilled map + classes, 1 fresh map + classes, 2 fresh
# map, 3 fresh map + classes with cold caches: each call after 64 MB were written and read, untimed;
# 4 fresh map + classes from the scan as float64 x y z rows, numpy's default dtype; 5 collapse_overhangs, 6 the
# same from float64 rows; default "0"), ROUNDS (400), REPS (20), TERRACUBE_DATA_DIR (else ../shared/data),
# SCAN (another cloud as KITTI-style float32 x y z i rows, e.g. written by terracube.io.write_kitti_bin). Each side's
# library sources are compiled with -Dterracube=tcA / tcB (so both link into one program); the list
# below is the map path's, extend it if a build misses a symbol.
set -euo pipefail

repo=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
base=${1:?usage: ab_builds.sh BASE [NEW]}
new=${2:-}
data=${TERRACUBE_DATA_DIR:-$repo/../shared/data}
kitti=${SCAN:-$data/kitti_seq00/velodyne/000000.bin}
[ -f "$kitti" ] || { echo "ab_builds.sh: $kitti not found (set TERRACUBE_DATA_DIR or SCAN)" >&2; exit 2; }
# The map path's sources; a revision compiles those it has (cpu_features, threads and
# quantize_kernels exist only before the simplification of issue 33).
sources="elevation_map cloud_frame cpu_features threads quantize_kernels collapse shadow_aware terrain"

work=$(mktemp -d)
cleanup() {
  git -C "$repo" worktree remove --force "$work/A" 2>/dev/null || true
  git -C "$repo" worktree remove --force "$work/B" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

git -C "$repo" worktree add -q --detach "$work/A" "$base"
if [ -n "$new" ]; then
  git -C "$repo" worktree add -q --detach "$work/B" "$new"
  tree_b=$work/B
else
  tree_b=$repo
fi

# -fopenmp for revisions before the library's own thread pool (bfb696c and earlier used OpenMP). Two
# threads across that change put both pools in one process, each spinning while the other works:
# compare such revisions on two threads in separate processes instead (bench_maps_cpp, alternately).
# Between revisions that both have the own pool, ab_maps.cpp lets the other side's threads fall
# asleep before each round (see there).
flags=(-std=c++17 -pthread -fopenmp -isystem /usr/include/eigen3)
# Both revisions are compiled in both namespaces and linked into two programs, the second with the
# sides swapped: code placement alone moves a side by up to about 5 % (an A/A run of one program
# reads 0.95-1.04), and the geometric mean of the two programs' new / base ratios cancels it.
compile() {  # compile TREE NAMESPACE OUTDIR
  mkdir -p "$3"
  for f in $sources; do
    [ -f "$1/cpp/src/$f.cpp" ] || continue
    g++ -O3 -DNDEBUG "${flags[@]}" -Dterracube=$2 -I "$1/cpp/include" -I "$1/cpp/src" -c "$1/cpp/src/$f.cpp" \
      -o "$3/$f.o" &
  done
  g++ -O2 "${flags[@]}" -Dterracube=$2 -DTERRACUBE_AB_SIDE=${2#tc} -I "$1/cpp/include" \
    -c "$repo/bench/cpp/ab_maps.cpp" -o "$3/side.o" &
  wait
}
compile "$work/A" tcA "$work/base_A"
compile "$tree_b" tcB "$work/new_B"
compile "$tree_b" tcA "$work/new_A"
compile "$work/A" tcB "$work/base_B"
link() {  # link A_OBJECTS B_OBJECTS PROGRAM
  g++ -O2 "${flags[@]}" "$repo/bench/cpp/ab_maps.cpp" "$1"/*.o "$2"/*.o -ltbb -o "$3"
}
link "$work/base_A" "$work/new_B" "$work/base_new"
link "$work/new_A" "$work/base_B" "$work/new_base"

echo "base = $(git -C "$repo" rev-parse --short "$base"), new = ${new:-working tree}; $(nproc) processors, $(lscpu | sed -n 's/^Model name: *//p')"
for what in ${WHAT:-0}; do
  for threads in ${THREADS:-1 2}; do
    first=$("$work/base_new" "$kitti" "$what" "$threads" "${ROUNDS:-400}" "${REPS:-20}")
    second=$("$work/new_base" "$kitti" "$what" "$threads" "${ROUNDS:-400}" "${REPS:-20}")
    echo "  A = base, B = new: $first"
    echo "  A = new, B = base: $second"
    r1=$(sed -n 's/.*B \/ A \([0-9.]*\) .*/\1/p' <<<"$first")
    r2=$(sed -n 's/.*B \/ A \([0-9.]*\) .*/\1/p' <<<"$second")
    awk -v a="$r1" -v b="$r2" -v w="$what" -v t="$threads" \
      'BEGIN { printf "what %s, %s thread(s): new / base = %.3f (geometric mean of %.3f and 1 / %.3f)\n", w, t, sqrt(a / b), a, b }'
  done
done
