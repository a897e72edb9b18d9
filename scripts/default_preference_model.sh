#!/usr/bin/env bash
# How hpgs_ns/assets/preference-default.pt (the `hpgs` selector's default model) is made. No human label is used:
# garden's human labels only score the recipe chosen, once, afterwards.
#
# Stage 1, renders (CPU, 8-15 min a scene on 2 cores; or the GPU at any size): oracle-labelled renders of the
#   six suite scenes (`hpgs bench --suite real6` finds them under DATA_ROOT), quarter size, 8 views, a render of
#   every view every 300 steps (the juice box: 2000 steps, every 400; it starts slower).
# Stage 2, the recipe (CPU; ~12 min with the features cached, ~30 min more without): leave one scene out over a
#   grid of backbone (alexnet, vgg16, both), feature transform (none, sqrt-l2), head L2 and training-pair policy;
#   the best mean same-step accuracy on the held-out scenes wins, is trained on all six scenes and scored on
#   garden's human labels. Also writes the six leave-one-scene-out models `hpgs bench --preference-models` takes.
#
#   bash scripts/default_preference_model.sh DATA_ROOT [PREF_DIR] [OUT]
set -euo pipefail
DATA_ROOT=${1:?usage: $0 DATA_ROOT [pref-dir] [out.pt]   (DATA_ROOT: the folder holding the suite scenes)}
PREF=${2:-pref}
OUT=${3:-hpgs_ns/assets/preference-default.pt}
declare -A STEPS=([juicebox]=2000) EVERY=([juicebox]=400)
for scene in bonsai juicebox stitch mold-gold-cape campus-building fox; do
  [ -f "$PREF/$scene/renders.csv" ] && continue
  data=$(python -c "from hpgs_lab.suites import load_suite; print(load_suite('real6', '$DATA_ROOT', ['$scene'])[0].path)")
  hpgs collect --data "$data" --out "$PREF/$scene" --downscale-factor 4 --num-views 8 --steps "${STEPS[$scene]:-1200}" \
      --every "${EVERY[$scene]:-300}" --rasterizer cpu
done
python benchmarks/pref_loso.py "$PREF"/{bonsai,juicebox,stitch,mold-gold-cape,campus-building,fox} \
    --feature-cache "$PREF/_features" --margins 0 0.05 --out benchmarks/results/pref_loso_recipes.json \
    --write-model "$OUT" --write-loso-models benchmarks/results/pref_models
