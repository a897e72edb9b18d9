#!/usr/bin/env bash
# Run `hpgs bench` sweeps ON the GPU machine in the background, so they go on between device calls while the
# machine stays held (30 min from its start), and hand back what has finished. Every call must carry .dev and the
# .devdata/<folder> of the scenes its sweeps still read (scripts/device_suite_data.py): a path a call does not name
# in its carry is gone on the machine afterwards. .dev and the tree are ~48 MB of the 64 MiB, so two scenes a call.
#   HPGS_GIT_COMMIT=<sha> bash scripts/device_sweep.sh start 'ARGS1' 'ARGS2' ...   # one `hpgs bench` per ARGS, in order
#   HPGS_GIT_COMMIT=<sha> bash scripts/device_sweep.sh parallel 'ARGS1' 'ARGS2'    # the same, all at once (one GPU shared)
#   bash scripts/device_sweep.sh collect SECONDS     # wait until the plan ends or SECONDS pass; results -> $OUT
# Every sweep writes to /tmp/suite (seeded with benchmarks/results/suite, so finished runs are skipped) with
# --data-root .devdata. `collect` packs every result JSON written since `start` into $OUT/results.tgz (the device
# tool returns at most 8 files) and the log into $OUT/sweep.log; unpack with
#   tar xzf /work/.device/<call>/results.tgz -C benchmarks/results/suite
set -o pipefail
cd "$(dirname "$0")/.."
bench=/tmp/suite
bench_one() {
  echo "=== start $(date +%s): $1"
  # shellcheck disable=SC2086  # ARGS is a list of words
  python3 -m hpgs_ns.cli bench --data-root .devdata --out "$bench" $1 2>&1 | grep --line-buffered -E 'PSNR|rror|failed|runs to do|Traceback|hpgs bench:'
  echo "=== end $(date +%s)"
}
case $1 in
start|parallel)
  mode=run
  [ "$1" = parallel ] && mode=runpar
  shift
  mkdir -p "$bench"
  cp -rn benchmarks/results/suite/. "$bench/" 2>/dev/null
  printf '%s\n' "$@" > /tmp/plan.txt
  # setsid: the sweep outlives this call (the device tool ends the call's own processes when it returns)
  setsid nohup bash scripts/device_sweep.sh $mode /tmp/plan.txt > /tmp/sweep.log 2>&1 < /dev/null &
  sleep 2
  echo "started: $(wc -l < /tmp/plan.txt) sweeps"
  ;;
run|runpar)
  # prelude once: installing the wheels again under a running sweep would pull its modules away
  source .dev/prelude.sh
  source scripts/device_env.sh
  while IFS= read -r args; do
    [ -z "$args" ] && continue
    if [ "$1" = runpar ]; then bench_one "$args" & else bench_one "$args"; fi
  done < "$2"
  wait
  echo "=== plan finished $(date +%s)"
  ;;
collect)
  end=$(($(date +%s) + $2))
  while [ "$(date +%s)" -lt "$end" ] && ! grep -q "plan finished" /tmp/sweep.log 2>/dev/null; do sleep 5; done
  (cd "$bench" && find . \( -name 'seed*.json' -o -name 'seed*-candidates.jsonl' \) -newer /tmp/plan.txt -not -path './_*' | tar czf "$OUT/results.tgz" -T -)
  cp /tmp/sweep.log "$OUT/sweep.log"
  tar tzf "$OUT/results.tgz" | wc -l
  tail -5 /tmp/sweep.log
  ;;
*)
  echo "usage: device_sweep.sh start ARGS... | collect SECONDS" >&2
  exit 2
  ;;
esac
