#!/usr/bin/env bash
# How hpgs_ns/assets/preference-default.pt (the `hpgs` selector's default model) is made.
#
# Stage 1, renders (GPU): train on 10 random bonsai views for 15000 steps, render every training camera every
#   2000 steps (1540 renders), score each against its photo, draw 1000 pairs. Small JPEG copies keep it movable.
#     hpgs collect --data mipnerf360-bonsai-device --downscale-factor 2 --out pref/bonsai \
#         --num-views 10 --steps 15000 --every 2000 --save-short-side 160 --pairs 1000
#   And on CPU, a synthetic scene (336 renders, 600 pairs, ~7 min on 2 cores):
#     hpgs make-scene --layout occluded --seed 1 --out pref/syn-scene
#     OMP_NUM_THREADS=1 hpgs collect --data pref/syn-scene --out pref/synthetic --num-views 8 --steps 800 --every 100 \
#         --pairs 600 --extra-args="--pipeline.model.warmup-length 100 --pipeline.model.refine-every 50 \
#         --pipeline.model.resolution-schedule 200 --pipeline.model.sh-degree-interval 130"
# Stage 2, labels and training (CPU, under a minute): LPIPS-oracle labels for the renders, plus the HP-GS authors'
#   human labels on garden; a frozen AlexNet (LPIPS weights) with a Bradley-Terry linear head.
set -euo pipefail
BONSAI_PAIRS=${1:?usage: $0 pref/bonsai pref/synthetic [shared/data/hpgs-pairs-garden] [out.pt]}
SYNTHETIC_PAIRS=${2:?usage: $0 pref/bonsai pref/synthetic [shared/data/hpgs-pairs-garden] [out.pt]}
GARDEN=${3:-../shared/data/hpgs-pairs-garden}
OUT=${4:-hpgs_ns/assets/preference-default.pt}
hpgs label "$BONSAI_PAIRS" --oracle lpips
hpgs label "$SYNTHETIC_PAIRS" --oracle lpips
hpgs train-pref --pairs "$BONSAI_PAIRS/pairs.csv" --pairs "$SYNTHETIC_PAIRS/pairs.csv" --pairs "$GARDEN/pairs.csv" \
    --out "$OUT" --backbone alexnet
hpgs eval-pref --model "$OUT" --pairs "$GARDEN/pairs.csv" --json
