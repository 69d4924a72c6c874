#!/usr/bin/env bash
# Runs every mesh-reader fuzzer and the scene fuzzer for a fixed time, seeded from tests/data and shared/data/meshes.
# Usage: run_fuzzers.sh BIN_DIR SECONDS [SHARED_DIR]. Fails if any fuzzer finds a crash.
set -euo pipefail
bin=$1
seconds=$2
shared=${3:-}
here=$(cd "$(dirname "$0")" && pwd)
data="$here/../data"
work=$(mktemp -d "${TMPDIR:-/tmp}/somasim-fuzz-XXXXXX")
trap 'rm -rf "$work"' EXIT

# seeds FORMAT GLOB...: copy matching small files into the corpus of FORMAT.
seeds() {
  local fmt=$1; shift
  mkdir -p "$work/$fmt"
  for f in "$@"; do
    [ -f "$f" ] || continue
    [ "$(stat -c %s "$f")" -le 65536 ] || continue
    cp "$f" "$work/$fmt/$(basename "$f")"
  done
}
seeds obj "$data"/obj/* "$shared"/data/meshes/*.obj
seeds stl "$data"/stl/*
seeds vtk_legacy "$data"/vtk/*.vtk "$shared"/data/meshes/*.vtk
seeds vtu "$data"/vtk/*.vtu "$shared"/data/meshes/*.vtu
seeds gmsh "$data"/gmsh/* "$shared"/data/meshes/*.msh
seeds scene "$data"/scenes/*
mkdir -p "$work/tetgen"
for node in "$data"/tetgen/*.node; do
  [ -f "$node" ] || continue
  base=${node%.node}
  { cat "$node"; printf '\0'; [ -f "$base.ele" ] && cat "$base.ele"; printf '\0';
    [ -f "$base.face" ] && cat "$base.face"; } > "$work/tetgen/$(basename "$base")"
done

# fuzz FORMAT: runs one fuzzer; its summary or its failure goes to $work/FORMAT.result.
fuzz() {
  local fmt=$1
  mkdir -p "$work/$fmt-artifacts"
  if ! "$bin/fuzz_$fmt" "$work/$fmt" -max_total_time="$seconds" -max_len=65536 \
        -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
        -artifact_prefix="$work/$fmt-artifacts/" > "$work/$fmt.log" 2>&1; then
    { echo "fuzz_$fmt FAILED:"; tail -n 60 "$work/$fmt.log"; } > "$work/$fmt.result"
    mkdir -p "${SOMASIM_FUZZ_ARTIFACTS:-/tmp/somasim-fuzz-artifacts}"
    cp "$work/$fmt-artifacts/"* "${SOMASIM_FUZZ_ARTIFACTS:-/tmp/somasim-fuzz-artifacts}/" 2>/dev/null || true
    return 1
  fi
  { echo "== fuzz_$fmt: ${seconds} s, $(ls "$work/$fmt" | wc -l) seed files"
    grep -E "stat::number_of_executed_units|stat::peak_rss_mb" "$work/$fmt.log" | tr '\n' ' '
    echo; } > "$work/$fmt.result"
}

# As many fuzzers at once as there are cores (each is single-threaded).
jobs=$(nproc 2>/dev/null || echo 2)
status=0
pids=()
fmts=()
for fmt in obj stl vtk_legacy vtu gmsh tetgen scene; do
  fuzz "$fmt" &
  pids+=($!)
  fmts+=("$fmt")
  if [ "${#pids[@]}" -ge "$jobs" ]; then
    wait "${pids[0]}" || status=1
    cat "$work/${fmts[0]}.result"
    pids=("${pids[@]:1}")
    fmts=("${fmts[@]:1}")
  fi
done
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || status=1
  cat "$work/${fmts[$i]}.result"
done
exit $status
