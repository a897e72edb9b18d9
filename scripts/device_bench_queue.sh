#!/usr/bin/env bash
# Fill one device call (at most 600 s) with bonsai bench runs; run ON the GPU machine, carrying [".dev"]:
#   bash scripts/device_bench_queue.sh 580 "320|--protocols fisherrf --selectors random --seeds 2" \
#       "240|--protocols hpgs --selectors farthest --seeds 0 --stress exposure pose-noise corrupt --max-runs 1"
# Each job is "ESTIMATED_SECONDS|hpgs bench arguments"; a job runs only if its estimate fits the time left (a run
# cut off midway is lost, and one left for later costs nothing). The committed results are copied in first, so
# finished runs are skipped (stress: the clean runs). Each new seed*.json lands in $OUT as soon as it is written,
# named by its path with "/" -> "_" and "+" -> "PLUS" (the device tool drops names with "+"); copy it back to
# benchmarks/results/bench/<scene>/<protocol>/<selector>/seed<k>.json, then
# `hpgs bench --out benchmarks/results/bench --report-only` (scripts/device_bench_collect.py does the copying).
# H100 walls: HP-GS protocol 200-260 s per run, FisherRF protocol 250-330 s (the first run on a fresh machine is
# the slowest).
set -o pipefail
cd "$(dirname "$0")/.."
source .dev/prelude.sh >/dev/null
source scripts/device_env.sh
budget=$1
shift
start=$(date +%s)
bench=/tmp/bench
mkdir -p "$bench"
cp -rn benchmarks/results/bench/. "$bench/" 2>/dev/null  # -n: keep runs already made here

out_name() { echo "${1#"$bench"/}" | tr / _ | sed 's/+/PLUS/g'; }

# Results of earlier calls on this (still warm) machine that may not have come back: only those not committed,
# since the device tool returns a few files per call.
find "$bench" -name 'seed*.json' | while read -r f; do
  cmp -s "$f" "benchmarks/results/bench/${f#"$bench"/}" || cp "$f" "$OUT/$(out_name "$f")"
done
touch /tmp/queue-start
(
  while sleep 3; do
    find "$bench" -newer /tmp/queue-start -name 'seed*.json' | while read -r f; do
      [ -f "$OUT/$(out_name "$f")" ] || cp "$f" "$OUT/$(out_name "$f")"
    done
  done
) &
copier=$!

for job in "$@"; do
  estimate=${job%%|*}
  args=${job#*|}
  left=$((budget - ($(date +%s) - start)))
  if [ "$estimate" -gt "$left" ]; then
    echo "SKIP ($left s left): $args"
    continue
  fi
  scenes="--scenes .dev/bonsai"
  [[ " $args " == *" --scenes "* ]] && scenes=""  # e.g. --scenes /tmp/bonsai-tracks --strict-init
  t0=$(date +%s)
  # shellcheck disable=SC2086  # word lists
  timeout "$left" python3 -m hpgs_ns.cli bench $scenes --no-references --downscale-factor 2 --out "$bench" $args 2>&1 | grep -E '  PSNR |rror' | tail -5
  echo "DONE $(($(date +%s) - t0)) s: $args"
done
sleep 4
kill "$copier"
ls "$OUT"
