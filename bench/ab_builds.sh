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
# map; default "0"), ROUNDS (400), REPS (20), TERRACUBE_DATA_DIR (else ../shared/data). Each side's
# library sources are compiled with -Dterracube=tcA / tcB (so both link into one program); the list
# below is the map path's, extend it if a build misses a symbol.
set -euo pipefail

repo=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
base=${1:?usage: ab_builds.sh BASE [NEW]}
new=${2:-}
data=${TERRACUBE_DATA_DIR:-$repo/../shared/data}
kitti=$data/kitti_seq00/velodyne/000000.bin
[ -f "$kitti" ] || { echo "ab_builds.sh: $kitti not found (set TERRACUBE_DATA_DIR)" >&2; exit 2; }
sources="elevation_map cloud_frame cpu_features threads quantize_kernels collapse terrain"

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

flags=(-std=c++17 -fopenmp -isystem /usr/include/eigen3)
for side in A B; do
  tree=$([ "$side" = A ] && echo "$work/A" || echo "$tree_b")
  mkdir -p "$work/obj$side"
  for f in $sources; do
    g++ -O3 -DNDEBUG "${flags[@]}" -Dterracube=tc$side -I "$tree/cpp/include" -I "$tree/cpp/src" \
      -c "$tree/cpp/src/$f.cpp" -o "$work/obj$side/$f.o" &
  done
  g++ -O2 "${flags[@]}" -Dterracube=tc$side -DTERRACUBE_AB_SIDE=$side -I "$tree/cpp/include" \
    -c "$repo/bench/cpp/ab_maps.cpp" -o "$work/obj$side/side.o" &
  wait
done
g++ -O2 "${flags[@]}" "$repo/bench/cpp/ab_maps.cpp" "$work"/objA/*.o "$work"/objB/*.o -loctomap -loctomath \
  -o "$work/ab_maps"

echo "A = $(git -C "$repo" rev-parse --short "$base"), B = ${new:-working tree}; $(nproc) processors, $(lscpu | sed -n 's/^Model name: *//p')"
for what in ${WHAT:-0}; do
  for threads in ${THREADS:-1 2}; do
    "$work/ab_maps" "$kitti" "$what" "$threads" "${ROUNDS:-400}" "${REPS:-20}"
  done
done
