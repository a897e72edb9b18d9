# Sourced ON the GPU machine by scripts/device_sweep.sh until the prelude has run there. The wheels the prelude
# installs (.dev/whl, 25 MiB) may come over several calls: scripts/device_calls.py cuts them into groups,
# .dev-whl/group-<k>/, each with whl.list (every wheel's name), prelude.sh and sitecustomize.py, once the working
# tree leaves no call room for all of them. A whole .dev (wheels, prelude, no list) still works.
# stage_wheels STAGE: keep what this call carried under STAGE/.dev (a carried path is gone after the next call);
# succeeds once every wheel whl.list names is there (without a list, what came with the prelude is all).
stage_wheels() {
  local stage=$1/.dev name dir
  mkdir -p "$stage/whl"
  for dir in .dev .dev-whl/group-*; do
    [ -d "$dir" ] || continue
    for name in "$dir"/whl/*.whl "$dir"/*.whl; do
      if [ -f "$name" ]; then cp -n "$name" "$stage/whl/"; fi
    done
    for name in whl.list prelude.sh sitecustomize.py; do
      if [ -f "$dir/$name" ]; then cp -n "$dir/$name" "$stage/"; fi
    done
  done
  [ -f "$stage/prelude.sh" ] && [ -f "$stage/sitecustomize.py" ] || return 1
  if [ -f "$stage/whl.list" ]; then
    while read -r name; do
      [ -z "$name" ] || [ -f "$stage/whl/$name" ] || return 1
    done < "$stage/whl.list"
  fi
  ls "$stage/whl/"*.whl > /dev/null 2>&1
}

# wheels_carried STAGE: "k of n wheels", for the log
wheels_carried() {
  local have total
  have=$(ls "$1/.dev/whl" 2>/dev/null | grep -c '\.whl$')
  total=$(grep -c . "$1/.dev/whl.list" 2>/dev/null || echo '?')
  echo "$have of $total wheels"
}
