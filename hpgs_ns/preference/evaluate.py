"""`hpgs eval-pref`: pair accuracy of a preference model on labelled pairs, and the helpers behind it."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List, Sequence, Tuple

import tyro
from rich.console import Console
from rich.progress import track
from typing_extensions import Annotated

from hpgs_ns.errors import UserError
from hpgs_ns.preference.pairs import Pair, PairsError, load_image, read_usable_pairs, require_pairs
from hpgs_ns.preference.recipe import PreferenceModelError

if TYPE_CHECKING:  # torch is imported where used: `hpgs eval-pref --help` imports this module
    import torch

    from hpgs_ns.preference.model import PreferenceModel

CONSOLE = Console(stderr=True)


def raw_features_of(model: PreferenceModel, paths: Sequence[Path], batch_size: int = 16,
                    progress: bool = True) -> torch.Tensor:
    """Pooled backbone features (before standardisation) of image files: N paths -> [N, F] on the CPU.

    Images are preprocessed one by one, then batched by size (renders of one scene share it)."""
    import torch

    with torch.no_grad():
        device = model.feature_mean.device
        out = torch.empty(len(paths), model.feature_dim)
        pending: Dict[Tuple[int, int], List[Tuple[int, torch.Tensor]]] = {}

        def flush(key: Tuple[int, int]) -> None:
            items = pending.pop(key)
            batch = torch.stack([x for _, x in items]).to(device)
            out[[i for i, _ in items]] = model.backbone(batch).float().cpu()

        steps = enumerate(paths)
        if progress and len(paths) > batch_size and CONSOLE.is_terminal:  # no stray blank lines in logs
            steps = track(steps, total=len(paths), description="features", console=CONSOLE, transient=True)
        for i, path in steps:
            x = model.preprocess(load_image(path)[None])[0]
            key = tuple(x.shape[-2:])
            pending.setdefault(key, []).append((i, x))
            if len(pending[key]) == batch_size:
                flush(key)
        for key in list(pending):
            flush(key)
        return out


def pair_accuracy_from_scores(scores: torch.Tensor, index: torch.Tensor, labels: torch.Tensor) -> float:
    """Fraction of pairs where the higher score is on the side labelled worse.

    scores: [N] per image; index: [P, 2] image indices (Image_1, Image_2); labels: [P], 1 = Image_1 worse.
    Exact ties count as half right."""
    import torch

    if len(labels) == 0:
        return float("nan")
    diff = scores[index[:, 0]] - scores[index[:, 1]]
    right = torch.where(diff == 0, torch.full_like(diff, 0.5), ((diff > 0).long() == labels.long()).float())
    return float(right.mean())


def index_pairs(pairs: Sequence[Pair]) -> Tuple[List[Path], torch.Tensor, torch.Tensor]:
    """(distinct images, [P, 2] indices into them, [P] labels) for labelled pairs."""
    import torch

    images = list(dict.fromkeys(p for pair in pairs for p in (pair.image_1, pair.image_2)))
    pos = {p: i for i, p in enumerate(images)}
    index = torch.tensor([[pos[p.image_1], pos[p.image_2]] for p in pairs], dtype=torch.long).reshape(-1, 2)
    labels = torch.tensor([int(p.label) for p in pairs], dtype=torch.long)
    return images, index, labels


def evaluate_pairs(model: PreferenceModel, pairs: Sequence[Pair], batch_size: int = 16,
                   progress: bool = True) -> Dict[str, float]:
    """{'accuracy', 'pairs', 'images'} of `model` on labelled, unskipped `pairs`."""
    import torch

    pairs = [p for p in pairs if p.usable]
    images, index, labels = index_pairs(pairs)
    with torch.no_grad():
        scores = model.score_features(model.standardise(raw_features_of(model, images, batch_size, progress).to(
            model.feature_mean.device))).cpu() if images else torch.empty(0)
    return {"accuracy": pair_accuracy_from_scores(scores, index, labels), "pairs": len(pairs), "images": len(images)}


@dataclass
class EvalPref:
    """Accuracy of a preference model on labelled pairs (which image of each pair is worse)."""

    model: Path
    """Checkpoint written by `hpgs train-pref`."""
    pairs: Annotated[Tuple[Path, ...], tyro.conf.UseAppendAction]
    """Pairs CSV (Image_1,Image_2,Human Preference[,Skipped]); repeat --pairs for several. Unlabelled and skipped
    rows are ignored."""
    json: bool = False
    """Print exactly one JSON object on stdout (accuracy, pairs, images, model, pairs_csv)."""
    batch_size: int = 16
    """Images per forward pass."""
    device: str = "cpu"
    """Torch device."""

    def main(self) -> None:
        from hpgs_ns.preference.model import PreferenceModel

        try:
            require_pairs(self.pairs)  # as train-pref: one line, before the model loads
            model = PreferenceModel.load(self.model, self.device)
            pairs = read_usable_pairs(self.pairs)
            result = evaluate_pairs(model, pairs, self.batch_size, progress=not self.json)
        except (PreferenceModelError, PairsError) as err:
            raise UserError(f"hpgs eval-pref: {err}") from None
        if result["pairs"] == 0:
            raise UserError(f"hpgs eval-pref: no labelled, unskipped pairs in {', '.join(map(str, self.pairs))}; "
                            "label some with `hpgs label`")
        result.update(model=str(self.model), pairs_csv=[str(p) for p in self.pairs], backbone=model.backbone_name)
        if self.json:
            sys.stdout.write(json.dumps(result) + "\n")
        else:
            print(f"{self.model}: {result['accuracy']:.1%} of {result['pairs']} pairs right "
                  f"({result['images']} images, backbone {model.backbone_name})")
