"""Shared by the selectors that score with a preference model (`hpgs`, `condorcet`, `blend`): their options, loading
the model, rendering views and running it in batches."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Dict, List, Optional, Sequence, Tuple

import torch

from hpgs_ns.selectors.base import SelectionContext, SelectionError, SelectorConfig


@dataclass
class PreferenceSelectorConfig(SelectorConfig):
    """The options every preference-model selector has."""

    uses_preference_model: ClassVar[bool] = True
    code_files: ClassVar[Tuple[str, ...]] = ("selectors/preference_features.py", "preference/model.py")
    model: Optional[Path] = None
    """Preference-model checkpoint (`hpgs train-pref`); default: the cross-scene model shipped with hpgs_ns."""
    batch_size: int = 16
    """Images per model forward."""
    render_short_side: Optional[int] = None
    """Short side of the renders fed to the model; default: the model's input size, or the views' own if smaller."""

DEFAULT_MODEL = Path(__file__).resolve().parent.parent / "assets" / "preference-default.pt"


def load_preference_model(path: Optional[Path], device: str = "cpu"):
    """Load a `hpgs train-pref` checkpoint (default: the model shipped in the package). One-line errors."""
    from hpgs_ns.preference.model import PreferenceModel
    from hpgs_ns.preference.recipe import PreferenceModelError

    path = Path(path) if path is not None else DEFAULT_MODEL
    if not path.is_file():
        hint = "train one with `hpgs train-pref`" if path != DEFAULT_MODEL else "reinstall hpgs-ns"
        raise SelectionError(f"preference model {path} not found; pass --pipeline.selection.hpgs.model PATH or {hint}")
    try:
        # The checkpoint overwrites the modules' random init: fork the RNG so that loading a model (which a
        # preference selector does at set-up) leaves the run's random stream, and so its splat, unchanged.
        with torch.random.fork_rng(devices=[]):
            return PreferenceModel.load(path, device=device).eval()
    except SelectionError:
        raise
    except PreferenceModelError as err:  # already names the file and the fix
        raise SelectionError(str(err)) from err
    except Exception as err:
        raise SelectionError(f"{path} is not a usable preference-model checkpoint ({err}); retrain with `hpgs train-pref`") from err


def _render_short_side(pref, requested: Optional[int], cameras) -> Optional[int]:
    """The short side to render `cameras` (one batch) at: `requested`, else the model's input size, or None (as they
    are) when no view of the batch is larger than that; a batch mixing sizes renders all at the input size. The
    model resizes every input to its size anyway, so rendering a small view larger only costs raster time (9.7x
    the pixels for 96x72 views); this way the model sees what its input recipe makes of the view at its own size,
    as for a photo."""
    if requested:
        return int(requested)
    target = int(getattr(pref, "input_size", 224))
    native = int(torch.minimum(cameras.width, cameras.height).max())
    return None if native <= target else target


@torch.no_grad()
def _batched(pref, context: SelectionContext, views: Sequence[int], short_side: Optional[int], batch: int, fn: str,
             work: Optional[Dict[str, float]] = None) -> torch.Tensor:
    pref.to(context.device)
    work = {} if work is None else work
    outs: List[torch.Tensor] = []
    for start in range(0, len(views), batch):
        chunk = list(views[start : start + batch])
        full = context.cameras[torch.tensor(chunk, dtype=torch.long)]
        renders = context.render(chunk, _render_short_side(pref, short_side, full))
        context.progress(len(chunk))
        for key, n in (("views_rendered", len(chunk)), ("pixels_rendered", sum(im.shape[0] * im.shape[1] for im in renders)),
                       ("pixels_full_resolution", int((full.width * full.height).sum())), ("model_forwards", len(chunk))):
            work[key] = work.get(key, 0) + n
        images = [pref.preprocess(im.permute(2, 0, 1)[None]) for im in renders]
        if len({tuple(im.shape) for im in images}) > 1:  # mixed aspect ratios: one forward per image
            outs += [getattr(pref, fn)(im).float().cpu() for im in images]
            continue
        x = torch.cat(images)
        # Pad to a fixed batch: with cudnn.benchmark (nerfstudio sets it) every new shape is re-autotuned.
        pad = batch - x.shape[0]
        if pad > 0:
            x = torch.cat([x, x[-1:].expand(pad, *x.shape[1:])])
        outs.append(getattr(pref, fn)(x)[: len(chunk)].float().cpu())
    if not outs:
        raise SelectionError("no views to run the preference model on")
    return torch.cat(outs)


def render_features(pref, context: SelectionContext, views: Sequence[int], short_side: Optional[int] = None, batch: int = 16,
                    work: Optional[Dict[str, float]] = None) -> torch.Tensor:
    """Preference features F(render) of `views`: [len(views), F]. Counts what it renders into `work`."""
    return _batched(pref, context, views, short_side, batch, "features", work)


def render_scores(pref, context: SelectionContext, views: Sequence[int], short_side: Optional[int] = None, batch: int = 16,
                  work: Optional[Dict[str, float]] = None) -> torch.Tensor:
    """Preference scores l(F(render)) of `views` (higher = worse reconstruction): [len(views)]. Counts into `work`."""
    return _batched(pref, context, views, short_side, batch, "score", work).reshape(-1)
