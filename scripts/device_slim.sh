#!/usr/bin/env bash
# Here, around a lease: every device call carries the whole working tree, and the committed benchmark results
# (thousands of small JSON files, ~48 MiB on disk as the tool counts) left too little of a call's 64 MiB for the
# lease's data. The GPU machine reads none of them but the preference models.
#   bash scripts/device_slim.sh out    # before the first call: move them to .dev-results/ (ignored, never carried)
#   bash scripts/device_slim.sh back   # after the lease, before merging: put them back (from git if need be)
set -euo pipefail
cd "$(dirname "$0")/.."
hold=.dev-results
case "${1:-}" in
out)
  if [ -n "$(git status --porcelain -- benchmarks/results)" ]; then
    echo "device_slim.sh: benchmarks/results has uncommitted changes; commit them before moving it out" >&2
    exit 1
  fi
  mkdir -p "$hold"
  for dir in benchmarks/results/*; do  # checked before anything moves: a half-done `out` is worse than none
    name=$(basename "$dir")
    if [ "$name" != pref_models ] && [ -e "$hold/$name" ]; then
      echo "device_slim.sh: $hold/$name is left from an earlier lease; run 'bash scripts/device_slim.sh back' first" >&2
      exit 1
    fi
  done
  for dir in benchmarks/results/*; do
    [ "$(basename "$dir")" = pref_models ] || mv "$dir" "$hold/"
  done
  echo "device_slim.sh: benchmark results held in $hold; run 'bash scripts/device_slim.sh back' after the lease"
  ;;
back)
  if [ -d "$hold" ]; then
    for dir in "$hold"/*; do
      [ -e "$dir" ] || continue
      name=$(basename "$dir")
      if [ -e "benchmarks/results/$name" ]; then
        # made during the lease (a merge of its results): its files are the newer, the hold fills in the rest
        cp -Rn "$dir/." "benchmarks/results/$name/"
        rm -rf "$dir"
      else
        mv "$dir" benchmarks/results/
      fi
    done
    rmdir "$hold" 2>/dev/null || true
  fi
  git checkout -- benchmarks/results  # anything the hold lacked, as last committed
  echo "device_slim.sh: benchmark results back; git status -- benchmarks/results:"
  git status --short -- benchmarks/results | head -n 5
  ;;
*)
  echo "usage: bash scripts/device_slim.sh out|back" >&2
  exit 2
  ;;
esac
