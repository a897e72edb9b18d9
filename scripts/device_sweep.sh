#!/usr/bin/env bash
# Run `hpgs bench` sweeps ON the GPU machine in the background, so they go on between device calls while the
# machine stays held (30 min from its start), and hand back what has finished. A machine's first call carries .dev;
# a call carries the .devdata/<folder> of the scenes it adds (scripts/device_suite_data.py). A carried path is gone
# on the machine after a call that does not name it, so each start copies .devdata into /tmp/devdata, which the
# sweeps read, and scripts/device_env.sh keeps the kernels, pycolmap and LPIPS weights in /tmp (which call carries
# what: scripts/device_calls.py): later calls carry other
# scenes, or one half of .dev-vgg each (VGG16, which `hpgs`, `condorcet` and `blend` need with the shipped
# preference model; start those sweeps once every part is there: `env` prints what the machine has).
# Chain the calls back to back: a machine idle for 30 s is given back, and the sweeps running on it die with it.
# Runs sharing a GPU run under CUDA MPS (`hpgs bench --mps auto`: the lent machines have nvidia-cuda-mps-control in
# /usr/local/nvidia/bin, and --runs-per-gpu then defaults to 12); pass --mps off in ARGS to compare without it.
#   HPGS_GIT_COMMIT=<sha> bash scripts/device_sweep.sh start 'ARGS1' 'ARGS2' ...   # one `hpgs bench` per ARGS, in order
#   HPGS_GIT_COMMIT=<sha> bash scripts/device_sweep.sh parallel 'ARGS1' 'ARGS2'    # the same, all at once (one GPU shared)
#   HPGS_GIT_COMMIT=<sha> bash scripts/device_sweep.sh then 'ARGS1' 'ARGS2'        # all at once, once the group before ends
#   bash scripts/device_sweep.sh commands 'CMD1' 'CMD2'    # whole command lines at once (device env set); write
#                                                    # results under /tmp/extra, collected into $OUT/extra.tgz
#   bash scripts/device_sweep.sh collect SECONDS     # wait until every group ends or SECONDS pass; results -> $OUT
#   bash scripts/device_sweep.sh env                 # keep what this call carried (kernels, weights, scenes) in /tmp
#   bash scripts/device_sweep.sh watch SECONDS DIR=N...  # `commands` results: every minute, count each /tmp/extra/DIR's
#                                                    # seed*.json and pack them all into $OUT/extra.tgz (temp, then
#                                                    # renamed: a call cut off still hands back the last pack), the
#                                                    # runs' worst-view JPEGs into $OUT/worst.tar; stop
#                                                    # once each DIR has its N or SECONDS pass
# Each start/parallel/then call adds a group (its own log, /tmp/sweep-N.log; its own copy of the code, /tmp/src-N,
# as the device tool rewrites the working tree on every call); groups started by `start` or
# `parallel` begin at once beside running ones. Every sweep writes to /tmp/suite (seeded with
# benchmarks/results/suite, so finished runs are skipped). `collect` packs every result JSON written since the
# first group into $OUT/results.tgz (the device tool returns at most 8 files) and the logs into $OUT/sweep.log;
# unpack with
#   tar xzf /work/.device/<call>/results.tgz -C benchmarks/results/suite     # or $HPGS_SWEEP_RESULTS
# HPGS_SWEEP_RESULTS=benchmarks/results/<folder> (same on every call, collect included) sweeps into another results
# folder than benchmarks/results/suite, e.g. runs whose settings differ from those already there.
set -o pipefail
cd "$(dirname "$0")/.."
results=${HPGS_SWEEP_RESULTS:-benchmarks/results/suite}
bench=/tmp/$(basename "$results")
data=/tmp/devdata
bench_one() {
  if [ -n "$HPGS_SWEEP_COMMANDS" ]; then  # `commands` groups: each line is a whole command, not hpgs bench ARGS
    echo "=== start $(date +%s): $1"; bash -c "$1" 2>&1 | tail -n 40; echo "=== end $(date +%s)"; return
  fi
  echo "=== start $(date +%s): $1"
  # shellcheck disable=SC2086  # ARGS is a list of words
  python3 -m hpgs_ns.cli bench --data-root "$data" --out "$bench" $1 2>&1 | grep --line-buffered -E 'PSNR|rror|failed|runs to do|Traceback|hpgs bench:'
  echo "=== end $(date +%s)"
}
device_env() {
  # prelude once per machine: installing the wheels again under a running sweep would pull its modules away; so
  # later calls set its exports here (.dev/prelude.sh comes with the workplace, read-only, exports and install in one).
  # It runs from a staging folder where the wheels gather, since they may come over several calls (device_wheels.sh).
  if [ ! -f /tmp/site/.prelude-done ]; then
    source scripts/device_wheels.sh
    if stage_wheels /tmp/prelude-stage; then
      (cd /tmp/prelude-stage && source .dev/prelude.sh) && touch /tmp/site/.prelude-done
    else
      echo "device_env: $(wheels_carried /tmp/prelude-stage) carried so far; the prelude runs once all have come"
    fi
  fi
  if [ -f /tmp/site/.prelude-done ]; then
    export PYTHONPATH=/tmp/site:$PWD PATH=/tmp/site/bin:$PATH TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
    export TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1
  fi
  source scripts/device_env.sh
}
keep_carried() {
  # here, not only in a sweep: what this call carried is gone after the next call that does not name it
  mkdir -p "$data"; [ -d .devdata ] && cp -rn .devdata/. "$data/"
  device_env
}
case $1 in
start|parallel|then|commands)
  mode=run
  [ "$1" != start ] && mode=runpar
  [ "$1" = commands ] && mode=runcmd
  after=0
  n=$(($(ls /tmp/plan-*.txt 2>/dev/null | wc -l) + 1))
  [ "$1" = then ] && after=$((n - 1))
  shift
  keep_carried
  # A fresh machine (a gap of over 30 s between calls) has lost earlier calls' carry: a sweep started then finds no
  # scenes and its whole call is lost, so refuse here (after this call's own carry is in), before anything starts.
  missing=
  [ -f /tmp/site/.prelude-done ] || missing="the wheels are not all here; "
  [ -n "$(ls -A "$data" 2>/dev/null)" ] || missing="${missing}no scenes in $data; "
  if [ -n "$missing" ]; then
    echo "device_sweep: not started: ${missing}carry them again (scripts/device_calls.py)"
    exit 3
  fi
  mkdir -p "$bench"
  [ -d "$results" ] && cp -rn "$results"/. "$bench/" 2>/dev/null
  [ -f /tmp/sweep.start ] || touch /tmp/sweep.start
  printf '%s\n' "$@" > "/tmp/plan-$n.txt"
  # The group runs from its own copy of the code: the device tool rewrites the working tree on every call, and a
  # run that imported hpgs_ns while it did failed (ModuleNotFoundError). Carried data stays out (.dev*, in /tmp).
  src=/tmp/src-$n
  mkdir -p "$src" && tar --exclude='./.dev*' --exclude=./.git -cf - . | tar -xf - -C "$src"
  # setsid: the sweep outlives this call (the device tool ends the call's own processes when it returns)
  (cd "$src" && setsid nohup bash scripts/device_sweep.sh $mode "/tmp/plan-$n.txt" "$after" > "/tmp/sweep-$n.log" 2>&1 < /dev/null &)
  sleep 2
  echo "group $n: $(wc -l < "/tmp/plan-$n.txt") sweeps$([ "$after" -gt 0 ] && echo ", after group $after"); scenes in $data: $(ls "$data" | tr '\n' ' ')"
  ;;
runcmd)
  HPGS_SWEEP_COMMANDS=1 exec bash scripts/device_sweep.sh runpar "$2" "$3"
  ;;
run|runpar)
  if [ "$3" -gt 0 ]; then
    echo "=== waiting for group $3 $(date +%s)"
    until grep -q "plan finished" "/tmp/sweep-$3.log" 2>/dev/null; do sleep 5; done
  fi
  device_env
  while IFS= read -r args; do
    [ -z "$args" ] && continue
    if [ "$1" = runpar ]; then bench_one "$args" & else bench_one "$args"; fi
  done < "$2"
  wait
  echo "=== plan finished $(date +%s)"
  ;;
env)
  keep_carried
  ;;
collect)
  if ! ls /tmp/sweep-*.log > /dev/null 2>&1; then
    echo "device_sweep.sh: no sweep on this machine (a fresh one: the machine that ran them was given back); start again" >&2
    exit 1
  fi
  end=$(($(date +%s) + $2))
  busy() { for log in /tmp/sweep-*.log; do grep -q "plan finished" "$log" || return 0; done; return 1; }
  while [ "$(date +%s)" -lt "$end" ] && busy; do sleep 5; done
  (cd "$bench" && find . \( -name 'seed*.json' -o -name 'seed*-candidates.jsonl*' \) -newer /tmp/sweep.start -not -path './_*' | tar czf "$OUT/results.tgz" -T -)
  # `commands` groups write their results under /tmp/extra (e.g. suggest_check.py --out /tmp/extra/suggest)
  [ -d /tmp/extra ] && (cd /tmp/extra && find . -name '*.json' -not -path '*/_*' | tar czf "$OUT/extra.tgz" -T -)
  for log in /tmp/sweep-*.log; do echo "##### $log"; cat "$log"; done > "$OUT/sweep.log"
  tar tzf "$OUT/results.tgz" | wc -l
  tail -n 4 /tmp/sweep-*.log
  ;;
watch)
  end=$(($(date +%s) + $2)); shift 2
  dirs=()
  for pair in "$@"; do dirs+=("${pair%%=*}"); done
  while :; do
    done_all=1; line="$(date +%T)"
    for pair in "$@"; do
      dir=${pair%%=*}; want=${pair#*=}
      n=$(find "/tmp/extra/$dir" -name 'seed*.json' -not -path '*/_*' 2>/dev/null | wc -l)
      line="$line $dir $n/$want"; [ "$n" -ge "$want" ] || done_all=0
    done
    echo "$line"
    (cd /tmp/extra && find "${dirs[@]}" -name '*.json' -not -path '*/_*' 2>/dev/null | tar czf "$OUT/extra.tmp.tgz" -T - \
      && mv "$OUT/extra.tmp.tgz" "$OUT/extra.tgz")
    # the runs' worst-view JPEGs in a pack of their own, so that their size never holds the results back (a file
    # over 16 MiB does not come back): every one while the pack stays under 15 MiB, else each run's worst alone
    for pattern in 'seed*-worst*.jpg' 'seed*-worst0.jpg'; do
      (cd /tmp/extra && find "${dirs[@]}" -name "$pattern" -not -path '*/_*' 2>/dev/null | tar cf "$OUT/worst.tmp.tar" -T -)
      if [ "$(stat -c %s "$OUT/worst.tmp.tar" 2>/dev/null || echo 0)" -lt 15728640 ]; then
        mv "$OUT/worst.tmp.tar" "$OUT/worst.tar"; break
      fi
      rm -f "$OUT/worst.tmp.tar"
    done
    [ "$done_all" = 1 ] && break
    [ $(($(date +%s) + 60)) -gt "$end" ] && break
    sleep 60
  done
  ;;
*)
  echo "usage: device_sweep.sh start|parallel|then ARGS... | commands CMD... | env | collect SECONDS | watch SECONDS DIR=N..." >&2
  exit 2
  ;;
esac
