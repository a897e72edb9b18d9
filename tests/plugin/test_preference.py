"""The preference model: Bradley-Terry maths, training on synthetic blur pairs, CSVs, checkpoints, eval-pref."""

from __future__ import annotations

import csv
import json
import math
import os
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import require_shared
from PIL import Image

from hpgs_ns.errors import UserError
from hpgs_ns.preference import model as pm
from hpgs_ns.preference.evaluate import EvalPref, evaluate_pairs
from hpgs_ns.preference.pairs import PairsError, image_disjoint_split, images_of, read_pairs, read_usable_pairs
from hpgs_ns.preference.train import TrainPref, paired_augment

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def alexnet_model() -> pm.PreferenceModel:
    return pm.PreferenceModel("alexnet", input_size=64).eval()


# --- Bradley-Terry --------------------------------------------------------------------------------------


def test_bt_probability_and_loss_match_hand_computation():
    s1, s2 = torch.tensor([2.0, -1.0, 0.3]), torch.tensor([0.5, 1.0, 0.3])
    y = torch.tensor([1, 0, 1])
    p = [1 / (1 + math.exp(-(a - b))) for a, b in zip(s1.tolist(), s2.tolist())]  # exp(x1)/(exp(x1)+exp(x2))
    assert p[2] == 0.5
    hand = -(math.log(p[0]) + math.log(1 - p[1]) + math.log(p[2])) / 3
    assert float(pm.bt_loss(s1, s2, y)) == pytest.approx(hand, rel=1e-6)
    # stable far in the tails, where log(sigmoid) would overflow to -inf
    far = pm.bt_loss(torch.tensor([1000.0, 0.0]), torch.tensor([0.0, 1000.0]), torch.tensor([0, 1]))
    assert float(far) == pytest.approx(1000.0)


def test_model_prob_worse_is_sigmoid_of_score_difference(alexnet_model):
    torch.manual_seed(0)
    with torch.no_grad():
        alexnet_model.head.weight.normal_(std=0.05)
        a, b = torch.rand(3, 3, 40, 60), torch.rand(3, 3, 40, 60)
        sa, sb = alexnet_model.score(a), alexnet_model.score(b)
        p = alexnet_model.prob_worse(a, b)
        assert torch.allclose(p, 1 / (1 + torch.exp(-(sa - sb))), atol=1e-6)
        assert torch.allclose(p + alexnet_model.prob_worse(b, a), torch.ones(3), atol=1e-6)
        assert alexnet_model.features(a).shape == (3, 2 * (64 + 192 + 384 + 256 + 256))
        assert torch.allclose(alexnet_model.score(a), alexnet_model.head(alexnet_model.features(a)).squeeze(-1))
        alexnet_model.head.weight.zero_()


def test_preprocess_recipe_resizes_short_side_and_is_idempotent(alexnet_model):
    x = torch.rand(2, 3, 210, 324)
    y = alexnet_model.preprocess(x)
    assert y.shape == (2, 3, 64, 99)
    assert torch.equal(alexnet_model.preprocess(y), y)
    with pytest.raises(ValueError):
        alexnet_model.preprocess(torch.rand(3, 64, 64))


def test_paired_augment_applies_the_same_flip_and_crop_to_both():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3, 40, 60)
    for _ in range(10):
        a, b = paired_augment(x, x.clone(), g)
        assert torch.equal(a, b) and a.shape[-1] >= 42
    big = torch.nn.functional.interpolate(x[None], scale_factor=2, mode="nearest")[0]
    a, b = paired_augment(x, big, torch.Generator().manual_seed(2))
    # the same relative box on different sizes (up to rounding)
    assert abs(b.shape[-2] - 2 * a.shape[-2]) <= 1 and abs(b.shape[-1] - 2 * a.shape[-1]) <= 1


# --- synthetic pairs: blurred is always worse -----------------------------------------------------------


def _texture(rng: np.random.Generator, h: int = 48, w: int = 64) -> np.ndarray:
    """A sharp random scene: smooth colour field plus hard-edged rectangles and fine noise."""
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.stack([0.5 + 0.3 * np.sin(rng.uniform(2, 9) * xx + rng.uniform(0, 6) + c * yy) for c in range(3)], -1)
    for _ in range(6):
        y0, x0 = rng.integers(0, h - 8), rng.integers(0, w - 8)
        img[y0 : y0 + rng.integers(4, 20), x0 : x0 + rng.integers(4, 20)] = rng.random(3)
    return np.clip(img + 0.08 * rng.standard_normal(img.shape), 0, 1)


def _blur(img: np.ndarray) -> np.ndarray:
    from torchvision.transforms.functional import gaussian_blur

    t = torch.from_numpy(img).permute(2, 0, 1).float()
    return gaussian_blur(t, kernel_size=9, sigma=2.5).permute(1, 2, 0).numpy()


def _blur_dataset(root: Path, n: int, seed: int, n_pairs: int) -> Path:
    """n sharp + n blurred images (of other scenes) and pairs sharp-vs-blurred in random order; labels say
    the blurred one is worse. Returns the CSV path."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        Image.fromarray((_texture(rng) * 255).astype(np.uint8)).save(root / f"sharp{i}.png")
        Image.fromarray((_blur(_texture(rng)) * 255).astype(np.uint8)).save(root / f"blur{i}.png")
    combos = [(i, j) for i in range(n) for j in range(n)]
    random.Random(seed).shuffle(combos)
    with open(root / "pairs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Image_1", "Image_2", "Human Preference", "Skipped"])
        for k, (i, j) in enumerate(combos[:n_pairs]):
            if k % 2:
                w.writerow([f"blur{j}.png", f"sharp{i}.png", 1, ""])
            else:
                w.writerow([f"sharp{i}.png", f"blur{j}.png", 0, ""])
        w.writerow(["sharp0.png", "blur0.png", "", ""])  # unlabelled: ignored
        w.writerow(["sharp1.png", "blur1.png", 1, 1])  # skipped, and mislabelled: must be ignored
    return root / "pairs.csv"


@pytest.fixture(scope="module")
def blur_data(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("blur")
    return {"train": _blur_dataset(root / "train", 30, 0, 600), "fresh": _blur_dataset(root / "fresh", 10, 1, 100),
            "root": root}


@pytest.fixture(scope="module")
def blur_model(blur_data) -> Path:
    out = blur_data["root"] / "model.pt"
    TrainPref(pairs=(blur_data["train"],), out=out, input_size=64).main()
    return out


def test_training_on_blur_pairs_generalises_to_unseen_images(blur_model, blur_data):
    ckpt = torch.load(blur_model, weights_only=True)
    held = ckpt["meta"]["heldout"]
    assert held["pairs"] >= 15 and held["accuracy"] > 0.95
    assert ckpt["backbone_state"] is None and blur_model.stat().st_size < 100_000  # frozen backbone not stored
    assert ckpt["input_recipe"]["resize_short_side"] == 64 and ckpt["backbone"] == "alexnet"
    assert ckpt["meta"]["training_data"]["pairs_csv"] == [str(blur_data["train"].resolve())]
    model = pm.PreferenceModel.load(blur_model)
    fresh = evaluate_pairs(model, read_usable_pairs([blur_data["fresh"]]), progress=False)
    assert fresh["pairs"] == 100 and fresh["accuracy"] > 0.95


def test_heldout_split_is_image_disjoint(blur_data):
    pairs = read_usable_pairs([blur_data["train"]])
    assert len(pairs) == 600  # the unlabelled and the skipped rows are not used
    train, test = image_disjoint_split(pairs, 0.2, seed=0)
    assert test and not set(images_of(train)) & set(images_of(test))
    assert len(set(images_of(test))) == 12


def test_checkpoint_round_trip_gives_identical_scores(tmp_path):
    """A model in memory, saved and loaded back, scores exactly as before. Every tensor the checkpoint carries (head,
    feature standardisation) is set away from its default, so a save or load that dropped one would show."""
    torch.manual_seed(0)
    model = pm.PreferenceModel("alexnet", input_size=40)
    with torch.no_grad():
        model.head.weight.normal_()
        model.head.bias.fill_(0.25)
        model.feature_mean.normal_()
        model.feature_std.uniform_(0.5, 2.0)
    model.meta = {"backbone_trained": False, "note": "round trip"}
    loaded = pm.PreferenceModel.load(model.save(tmp_path / "model.pt"))
    x = torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        before, after = model.score(x), loaded.score(x)
        default = pm.PreferenceModel("alexnet", input_size=40).score(x)
    assert after.shape == (3,) and torch.equal(before, after)
    assert not torch.allclose(default, before)  # the scores tell a model with these weights from a default one
    assert (loaded.backbone_name, loaded.input_size, loaded.meta) == ("alexnet", 40, model.meta)


def test_eval_pref_json_prints_exactly_one_object(blur_model, blur_data):
    proc = subprocess.run(
        [sys.executable, "-m", "hpgs_ns.cli", "eval-pref", "--model", str(blur_model), "--pairs", str(blur_data["fresh"]), "--json"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)  # the whole of stdout is one JSON object
    assert isinstance(result, dict) and proc.stdout.count("\n") == 1
    assert 0.95 < result["accuracy"] <= 1 and result["pairs"] == 100


def test_finetune_trains_and_stores_the_backbone(blur_data, tmp_path):
    rows = read_pairs(blur_data["train"])[:8]
    small = blur_data["train"].parent / "small.csv"
    with open(small, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Image_1", "Image_2", "Human Preference"])
        w.writerows([p.image_1.name, p.image_2.name, p.label] for p in rows)
    out = tmp_path / "ft.pt"
    cmd = TrainPref(pairs=(small,), out=out, input_size=32, finetune=True, epochs=1, batch_size=4, test_fraction=0)
    trained = cmd.run()
    before = pm.PreferenceModel("alexnet", input_size=32).backbone.state_dict()
    after = trained.backbone.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)  # the backbone moved
    trained.save(out)
    ckpt = torch.load(out, weights_only=True)
    assert ckpt["backbone_state"] is not None and ckpt["meta"]["backbone_trained"]
    loaded = pm.PreferenceModel.load(out)
    x = torch.rand(2, 3, 32, 40)
    with torch.no_grad():
        assert torch.allclose(loaded.score(x), trained.score(x), atol=1e-5)


# --- one-line errors ------------------------------------------------------------------------------------


@pytest.mark.parametrize("content, expect", [
    ("A,B,C\nx.png,y.png,1\n", "missing column"),
    ("Image_1,Image_2,Human Preference\nx.png,y.png,2\n", "bad.csv:2"),
    ("Image_1,Image_2,Human Preference\nx.png,y.png,1,9\n", "too many cells"),
    ("Image_1,Image_2,Human Preference\n,y.png,1\n", "empty image name"),
    ("Image_1,Image_2,Human Preference,Skipped\nx.png,y.png,1,yes\n", "Skipped"),
])
def test_malformed_csv_gives_one_line_error(tmp_path, content, expect):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(PairsError) as info:
        read_pairs(path)
    assert expect in str(info.value) and "\n" not in str(info.value) and str(path) in str(info.value)
    with pytest.raises(UserError, match=r"^hpgs train-pref: ") as info:
        TrainPref(pairs=(path,), out=tmp_path / "m.pt").main()
    assert "\n" not in str(info.value) and expect in str(info.value) and str(path) in str(info.value)
    assert not (tmp_path / "m.pt").exists()


def test_missing_image_gives_one_line_error(tmp_path):
    Image.new("RGB", (8, 8)).save(tmp_path / "x.png")
    (tmp_path / "p.csv").write_text("Image_1,Image_2,Human Preference\nx.png,gone.png,1\n")
    with pytest.raises(UserError, match=r"^hpgs train-pref: .*missing") as info:
        TrainPref(pairs=(tmp_path / "p.csv",), out=tmp_path / "m.pt").main()
    assert "\n" not in str(info.value) and str(tmp_path / "gone.png") in str(info.value)
    assert not (tmp_path / "m.pt").exists()


def test_wrong_checkpoints_give_one_line_errors(tmp_path, blur_model, blur_data, capsys):
    cases = {}
    (tmp_path / "text.pt").write_text("not a checkpoint")
    cases["text.pt"] = "not a readable checkpoint"
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    cases["other.pt"] = "not an hpgs preference-model checkpoint"
    ckpt = torch.load(blur_model, weights_only=True)
    torch.save({**ckpt, "backbone": "vgg16"}, tmp_path / "mismatch.pt")
    cases["mismatch.pt"] = "does not match the vgg16 backbone"
    torch.save({**ckpt, "version": 99}, tmp_path / "future.pt")
    cases["future.pt"] = "version 99"
    cases["absent.pt"] = "no such preference-model checkpoint"
    for name, expect in cases.items():
        with pytest.raises(pm.PreferenceModelError) as info:
            pm.PreferenceModel.load(tmp_path / name)
        assert expect in str(info.value) and "\n" not in str(info.value) and name in str(info.value)
    with pytest.raises(UserError, match=r"^hpgs eval-pref: .*mismatch\.pt.*does not match the vgg16 backbone"):
        EvalPref(model=tmp_path / "mismatch.pt", pairs=(blur_data["fresh"],), json=True).main()
    assert capsys.readouterr().out == ""
    # The CLI prints it as one `error:` line on stderr, nothing on stdout (--json readers see no half output), exit 1.
    proc = subprocess.run(
        [sys.executable, "-m", "hpgs_ns.cli", "eval-pref", "--model", str(tmp_path / "mismatch.pt"), "--pairs",
         str(blur_data["fresh"]), "--json"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: hpgs eval-pref: "), proc.stderr
    assert "mismatch.pt" in proc.stderr and "does not match the vgg16 backbone" in proc.stderr


def test_resnet34_without_cached_weights_says_how_to_proceed(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(pm.BackboneUnavailable) as info:
        pm.build_backbone("resnet34", pretrained=True)
    assert "--pretrained none" in str(info.value) and "\n" not in str(info.value)
    scratch = pm.PreferenceModel("resnet34", pretrained=False, input_size=32)
    assert scratch.features(torch.rand(1, 3, 32, 32)).shape == (1, 1024)
    assert scratch.checkpoint()["backbone_state"] is not None  # trained-from-scratch weights must be stored


def test_efficientnet_lite0_backbone_from_package_weights():
    model = pm.PreferenceModel("efficientnet-lite0", input_size=64).eval()
    with torch.no_grad():
        f = model.features(torch.rand(2, 3, 64, 80))
    assert f.shape == (2, 2560) and torch.isfinite(f).all()
    assert model.checkpoint()["backbone_state"] is None


def test_joined_backbone_with_sqrt_l2_has_unit_norm_parts_and_survives_a_checkpoint(tmp_path):
    """(That these are the features the recipe search fitted its heads on: tests/lab/test_pref_loso.py.)"""
    images = torch.rand(2, 3, 48, 64)
    joined = pm.PreferenceModel("alexnet+vgg16", input_size=48, feature_transform="sqrt-l2").eval()
    with torch.no_grad():
        raw = joined.raw_features(images)
    assert raw.shape == (2, 2304 + 2944)
    # each trunk's part has unit norm and no negative entries
    assert torch.allclose(raw[:, :2304].norm(dim=1), torch.ones(2), atol=1e-5) and (raw >= 0).all()
    assert torch.allclose(raw[:, 2304:].norm(dim=1), torch.ones(2), atol=1e-5)
    zeros = torch.zeros(2, 5, requires_grad=True)  # dead channels: the transform's gradient stays finite
    pm.transform_pooled(zeros, "sqrt-l2").sum().backward()
    assert torch.isfinite(zeros.grad).all()
    joined.head.weight.data.normal_()
    joined.save(tmp_path / "m.pt")
    back = pm.PreferenceModel.load(tmp_path / "m.pt")
    assert (back.backbone_name, back.feature_transform) == ("alexnet+vgg16", "sqrt-l2")
    with torch.no_grad():
        assert torch.allclose(back.score(images), joined.score(images), atol=1e-5)


def test_a_checkpoint_from_before_transforms_reads_as_none_and_a_bad_pairing_is_one_line(tmp_path, blur_model):
    ckpt = torch.load(blur_model, weights_only=True)
    ckpt.pop("feature_transform", None)
    torch.save(ckpt, tmp_path / "old.pt")
    assert pm.PreferenceModel.load(tmp_path / "old.pt").feature_transform == "none"
    torch.save({**ckpt, "feature_transform": "cube-root"}, tmp_path / "odd.pt")
    with pytest.raises(pm.PreferenceModelError, match="odd.pt: unknown feature transform 'cube-root'"):
        pm.PreferenceModel.load(tmp_path / "odd.pt")
    (tmp_path / "p.csv").write_text("Image_1,Image_2,Human Preference\na.png,b.png,1\nc.png,d.png,0\n")
    with pytest.raises(UserError, match=r"^hpgs train-pref: .*--feature-transform none") as info:
        TrainPref(pairs=(tmp_path / "p.csv",), out=tmp_path / "m.pt", backbone="resnet34", pretrained="none",
                  feature_transform="sqrt-l2").main()
    assert "\n" not in str(info.value) and not (tmp_path / "m.pt").exists()


@pytest.mark.shipped_model
def test_the_shipped_default_never_saw_garden_and_scores_its_record_on_the_garden_human_labels():
    """Issue 21: the default model, chosen leave one scene out on oracle-labelled renders of the suite scenes,
    agrees with the HP-GS authors' human labels on garden (a scene it never saw) at least 85% of the time, as its
    own record says. (That record is the recipe search's: tests/lab/test_pref_loso.py.)"""
    from hpgs_ns.selectors.preference_features import DEFAULT_MODEL

    garden = require_shared("data", "hpgs-pairs-garden", "pairs.csv")
    model = pm.PreferenceModel.load(DEFAULT_MODEL)
    meta = model.meta
    assert (model.backbone_name, model.feature_transform) == (meta["recipe"]["backbone"], meta["recipe"]["feature_transform"])
    assert meta["training_data"]["human_labels"].startswith("none")
    assert not any("garden" in s for s in meta["training_data"]["oracle_scenes"])
    torch.set_num_threads(min(4, os.cpu_count() or 1))
    result = evaluate_pairs(model, read_usable_pairs([garden]), progress=False)
    assert result["pairs"] == 1485
    assert result["accuracy"] == pytest.approx(meta["garden_human_accuracy"], abs=0.002)
    assert result["accuracy"] >= 0.85
