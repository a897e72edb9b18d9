"""What the preference commands name without loading torch: the backbone and feature-transform choices (tyro's
options of `hpgs train-pref`) and the checkpoint error `hpgs label` and `hpgs eval-pref` catch.

`model` defines the model itself and re-exports these, so `hpgs_ns.preference.model.BackboneName` and
`model.PreferenceModelError` are the same objects; they live here so that `hpgs train-pref --help` and `hpgs label
--help` import no torch.
"""

from __future__ import annotations

from typing import Literal

from hpgs_ns.errors import UserError

# Literals so that tyro's choices (`hpgs train-pref --backbone`) and the checks in `model` come from one list
BackboneName = Literal["alexnet", "vgg16", "efficientnet-lite0", "resnet34", "alexnet+vgg16"]
FeatureTransform = Literal["none", "sqrt-l2"]


class PreferenceModelError(UserError, ValueError):
    """A preference-model checkpoint is missing, corrupt or does not match this code (one-line message)."""
