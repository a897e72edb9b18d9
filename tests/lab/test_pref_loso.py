"""benchmarks/pref_loso.py, the leave-one-scene-out recipe search behind the shipped preference model: the features
it fits its heads on are the shipped recipe's, and the shipped model is the one its record names. (The model itself:
tests/plugin/test_preference.py.)"""

from __future__ import annotations

import json

import pytest
import torch
from conftest import REPO
from helpers import load_script

from hpgs_ns.preference import model as pm

RECORD = REPO / "benchmarks" / "results" / "pref_loso_recipes.json"


def test_the_recipe_search_features_are_the_joined_backbones():
    """What the search fitted its heads on (each trunk's pooled features, transformed, side by side) is what
    `PreferenceModel("alexnet+vgg16", feature_transform="sqrt-l2").raw_features` computes."""
    recipe_features = load_script(REPO / "benchmarks" / "pref_loso.py").recipe_features
    images = torch.rand(2, 3, 48, 64)
    joined = pm.PreferenceModel("alexnet+vgg16", input_size=48, feature_transform="sqrt-l2").eval()
    trunks = {name: pm.PreferenceModel(name, input_size=48).eval() for name in ("alexnet", "vgg16")}
    with torch.no_grad():
        raw = joined.raw_features(images)
        searched = recipe_features({n: m.raw_features(images) for n, m in trunks.items()}, "alexnet+vgg16", "sqrt-l2")
    assert raw.shape == (2, 2304 + 2944) and torch.allclose(raw, searched, atol=1e-6)


@pytest.mark.shipped_model
def test_the_shipped_default_is_the_recipe_and_garden_score_the_search_recorded():
    """Issue 21: the shipped default's recipe, and its score on garden's human labels, are those of the search's
    record (`benchmarks/results/pref_loso_recipes.json`), which compared more than one recipe."""
    from hpgs_ns.selectors.preference_features import DEFAULT_MODEL

    if not RECORD.is_file():
        pytest.skip(f"{RECORD} not found")
    record = json.loads(RECORD.read_text())
    meta = torch.load(DEFAULT_MODEL, map_location="cpu", weights_only=True)["meta"]
    assert meta["recipe"] == record["recipe"] and record["recipes_compared"] >= 2
    assert record["garden_pairs"] == 1485
    assert meta["garden_human_accuracy"] == pytest.approx(record["garden_human_accuracy"], abs=0.002)
