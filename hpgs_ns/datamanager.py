"""The active datamanager: trains on a growing subset of the training views.

Built on nerfstudio's `FullImageDatamanager`. The training split is divided into *active* views (sampled for
training) and withheld *candidates*; the test split is neither, ever. The selection rounds (`hpgs_ns.rounds`)
decide when views join and which; this class owns the split, the sampling of training views, and the state that
checkpoints keep: the active set and the round history (`get_extra_state`), restored by `--load-dir`, `ns-eval`
and `ns-viewer`.

Views are named by their image's path relative to the data root (`hpgs_ns.dataparser.view_name`): Blender's
train and test splits both hold `r_0.png`. The test split is the dataparser's own; a test view is never active
and never a candidate, and a split with no test views (`--eval-mode all`) or test views that are also training
views is an error.

Its config also carries the rounds' and the selectors' options (`--pipeline.datamanager.select-every`,
`--pipeline.datamanager.<selector>.*`), where users set them.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns.dataparser import DataParserUnion, MipNerf360DataParserConfig, SceneDataError, view_name
from hpgs_ns.errors import UserError
from hpgs_ns.selectors import (
    BlendSelectorConfig,
    CondorcetSelectorConfig,
    FarthestSelectorConfig,
    FisherSelectorConfig,
    HpgsSelectorConfig,
    RandomSelectorConfig,
    SelectorConfig,
    registry,
)
from hpgs_ns.selectors.farthest import farthest_point_order

# Every registered selector, built-in or from another package's entry point (read once, at import).
SelectorName = Literal[tuple(registry.selector_names())]  # type: ignore[valid-type]


class ActiveViewError(UserError, RuntimeError):
    """The active/withheld split cannot be set up or restored."""


@dataclass
class ActiveDatamanagerConfig(FullImageDatamanagerConfig):
    """Full-image datamanager that starts from a few views and adds the views a selector picks."""

    _target: Type = field(default_factory=lambda: ActiveDatamanager)
    dataparser: DataParserUnion = field(default_factory=MipNerf360DataParserConfig)
    """Which dataparser reads the scene (a subcommand: `mipnerf360`, the default, `nerfstudio-data`, `colmap`,
    `blender-data`, ...), with its options after it."""
    cache_images_type: Literal["uint8", "float32"] = "uint8"
    num_initial_views: int = 20
    """Training views active at step 0."""
    initial_views: Literal["even", "fps", "random"] = "even"
    """How the initial views are chosen: evenly spaced along the capture (file-name order); `fps`: the first
    view, then farthest camera centres (FisherRF's start); or uniformly at random (seeded)."""
    exclude_views: Tuple[str, ...] = ()
    """Training views left out of the run entirely, never active and never candidates: a capture that lacks them
    (`benchmarks/suggest_check.py` withholds arcs of a capture this way)."""
    initial_view_names: Tuple[str, ...] = ()
    """Explicit initial views by name (image path relative to the data root, e.g. `images/0001.png`, or just the
    file name where that is unambiguous); overrides initial-views."""
    select_every: int = 2000
    """A selection round runs at steps select_every, 2*select_every, ... (never at step 0)."""
    select_at: Tuple[int, ...] = ()
    """Explicit round steps (e.g. FisherRF's 400 900 1500 ...); when given, select-every is ignored."""
    views_per_round: int = 1
    """Views added per round (greedy batch selection when > 1)."""
    max_rounds: int = 7
    """Rounds before selection stops (HP-GS: 7 additions over 15000 steps)."""
    seed: int = 0
    """Seeds the initial views (random/fps) and the selectors' randomness."""
    selector: SelectorName = "hpgs"
    """Which selector picks the next views (default: the paper's human-preference selector). Other packages add
    selectors through the `hpgs_ns.selectors` entry point group."""
    # One option group per built-in selector (hpgs_ns.selectors.registry.BUILTIN_SELECTORS; a test checks they match).
    random: RandomSelectorConfig = field(default_factory=RandomSelectorConfig)
    """Options of the `random` selector."""
    farthest: FarthestSelectorConfig = field(default_factory=FarthestSelectorConfig)
    """Options of the `farthest` selector."""
    fisher: FisherSelectorConfig = field(default_factory=FisherSelectorConfig)
    """Options of the `fisher` selector (FisherRF)."""
    hpgs: HpgsSelectorConfig = field(default_factory=HpgsSelectorConfig)
    """Options of the `hpgs` selector (the paper's method)."""
    condorcet: CondorcetSelectorConfig = field(default_factory=CondorcetSelectorConfig)
    """Options of the `condorcet` selector (the paper's ablation)."""
    blend: BlendSelectorConfig = field(default_factory=BlendSelectorConfig)
    """Options of the `blend` selector (farthest + hpgs, weights fitted on candidate logs)."""
    strict_init: bool = False
    """Keep only the COLMAP seed points whose track includes at least two initial views, so withheld and test
    views leak no geometry into the starting splat."""
    eval_each_round: bool = False
    """Measure test-view PSNR just before each round (recorded in selected_views.json; used by `hpgs bench`)."""
    stop_when_gain_below: Optional[float] = None
    """Stop selecting once the next view's predicted test-PSNR gain (dB) is below this (`hpgs_ns.early_stop`;
    default: every round runs): views a scene does not need are not added."""
    gain_model: Optional[Path] = None
    """The gain calibration for stop-when-gain-below (`benchmarks/early_stop.py --write-model`; default:
    hpgs_ns/assets/gain-model.json, fitted on the suite's FisherRF-protocol runs)."""
    log_candidate_scores: bool = False
    """After each round, log every built-in selector's score of every candidate and each candidate's render error
    against its withheld photo to candidate_scores.jsonl (analysis only: never read by the run, and its random
    stream is left as it was)."""
    snapshot_every: int = 0
    """If > 0, every this many steps (and at the last step) render every training-split view to
    `<run dir>/snapshots/step-NNNNNN/` (what `hpgs collect` labels). Test views are never rendered."""
    selection_short_side: Optional[int] = None
    """Default render size (short side, pixels) for selectors that render views; None = dataset resolution."""
    reset_after_add: bool = False
    """After each round, start training over from the new view set, as FisherRF (Jiang et al., ECCV 2024) does:
    the Gaussians go back to the step-0 ones, optimizer moments, densification state and camera optimizer are
    cleared, and learning rates and splatfacto's step-keyed schedule (densification, opacity reset, SH degree,
    resolution) restart at the round's step. The trainer's step keeps counting; the run ends at
    max-num-iterations."""

    def __setstate__(self, state: dict) -> None:
        # A config.yml saved before an option group existed (PyYAML restores attributes, not __init__) gets that
        # group's defaults; plain-valued options already fall back to their class defaults.
        self.__dict__.update(state)
        for f in fields(self):
            if f.name not in self.__dict__ and f.default_factory is not MISSING:
                setattr(self, f.name, f.default_factory())

    def selector_config(self) -> SelectorConfig:
        """The options of the chosen selector: its group above for a built-in one, else the registry's."""
        own = getattr(self, self.selector, None)
        return own if isinstance(own, SelectorConfig) else registry.selector_config(self.selector)


class ActiveDatamanager(FullImageDatamanager):
    """Samples training batches from the active views only and grows them by selection rounds."""

    config: ActiveDatamanagerConfig

    def __init__(self, config: ActiveDatamanagerConfig, device="cpu", test_mode="val", **kwargs):
        if torch.device(device).type == "cpu":
            # "gpu" caching means "on the datamanager's device"; "cpu" caching pins memory, which needs CUDA.
            config.cache_images = "gpu"
        if getattr(config.dataparser, "eval_mode", None) == "all":
            raise ActiveViewError(
                "--eval-mode all trains on the test views too, so nothing is withheld for testing; use the dataparser's "
                "default split (e.g. nerfstudio-data --eval-mode fraction, or interval)"
            )
        try:
            super().__init__(config, device=device, test_mode=test_mode, **kwargs)
        except AssertionError as err:  # nerfstudio checks each image's size against its camera's while caching
            if "does not match the camera parameters" not in str(err):
                raise
            raise SceneDataError(
                f"{err}: the images were downscaled with another rounding than the cameras; pass the dataparser's "
                "--downscale-rounding-mode (floor, round or ceil) that made them, or delete the images_N folder"
            ) from None
        root = Path(self.config.dataparser.data)
        self.image_names: List[str] = [view_name(p, root) for p in self.train_dataset.image_filenames]
        overlap = set(self.test_view_names) & set(self.image_names)
        if overlap:
            raise ActiveViewError(
                f"{len(overlap)} test views are also training views (e.g. {sorted(overlap)[0]}): the dataparser's split "
                "overlaps; choose a split that holds test views out (--eval-mode fraction, interval or filename)"
            )
        self.generator = torch.Generator().manual_seed(self.config.seed)
        self.excluded = {self._view_index(v, "excluded") for v in self.config.exclude_views}
        self.active: List[int] = self._initial_views()
        self.history: List[Dict[str, Any]] = []
        if self.config.strict_init:
            self._keep_points_seen_by_initial_views()
        self.train_unseen_cameras = self.sample_train_cameras()

    # ---- which views are active ----------------------------------------------------------------------------

    @property
    def candidates(self) -> List[int]:
        """Withheld training views, in index order."""
        active = set(self.active) | getattr(self, "excluded", set())
        return [i for i in range(len(self.train_dataset)) if i not in active]

    @property
    def initial_views(self) -> List[int]:
        """Active views that no round added."""
        added = {i for h in self.history for i in h["chosen_indices"]}
        return [i for i in self.active if i not in added]

    @property
    def test_view_names(self) -> List[str]:
        return [view_name(p, Path(self.config.dataparser.data)) for p in self.eval_dataset.image_filenames]

    def activate(self, indices: Sequence[int]) -> None:
        """Make withheld views active (they are sampled from the next training pass on)."""
        self.active = sorted(self.active + [int(i) for i in indices])
        self.train_unseen_cameras = self.sample_train_cameras()

    def _initial_views(self) -> List[int]:
        allowed = [i for i in range(len(self.train_dataset)) if i not in self.excluded]
        n, k = len(allowed), self.config.num_initial_views
        if self.config.initial_view_names:
            chosen = sorted(self._view_index(v, "initial") for v in self.config.initial_view_names)
            if self.excluded & set(chosen):
                raise ActiveViewError(f"initial view {self.image_names[min(self.excluded & set(chosen))]!r} is also excluded; drop it from one list")
            return chosen
        if k < 1:
            raise ActiveViewError("--pipeline.datamanager.num-initial-views must be at least 1")
        if k >= n:
            CONSOLE.print(f"[yellow]num-initial-views={k} >= {n} training views: training on all of them")
            return allowed
        if self.config.initial_views == "even":
            return sorted({allowed[int(round(x))] for x in np.linspace(0, n - 1, k)})
        if self.config.initial_views == "random":
            return sorted(allowed[i] for i in torch.randperm(n, generator=self.generator)[:k].tolist())
        centres = self.train_dataset.cameras.camera_to_worlds[torch.tensor(allowed), :3, 3]
        return sorted(allowed[i] for i in farthest_point_order(centres, k, start=0))

    def _view_index(self, name: str, role: str = "initial") -> int:
        """Index of the training view called `name` (its full name, or its file name if no other view has it)."""
        if name in self.image_names:
            return self.image_names.index(name)
        matches = [i for i, n in enumerate(self.image_names) if Path(n).name == name]
        if len(matches) == 1:
            return matches[0]
        if matches:
            raise ActiveViewError(f"{role} view {name!r} names several views; write it whole, e.g. {self.image_names[matches[0]]!r}")
        raise ActiveViewError(f"{role} view {name!r} is not a training view (test views cannot be used)")

    def _keep_points_seen_by_initial_views(self, min_views: int = 2) -> None:
        """Filter the dataparser's seed points in place (the pipeline hands them to the model after this)."""
        # nerfstudio's own COLMAP reader, as its dataparser used: the mask then lines up with its point order.
        from hpgs_ns.scenes.colmap_model import read_images, read_points3D

        parser = self.config.dataparser
        if not hasattr(parser, "colmap_path"):
            raise ActiveViewError(
                "strict-init needs COLMAP point tracks (which images see each point), which only COLMAP scenes have "
                "(the mipnerf360 or colmap dataparser); drop --pipeline.datamanager.strict-init"
            )
        meta = self.train_dataparser_outputs.metadata
        if "points3D_xyz" not in meta:
            return
        model_dir = Path(parser.data) / parser.colmap_path
        images, points = read_images(model_dir), read_points3D(model_dir)
        if images is None or points is None:
            raise ActiveViewError(f"strict-init needs {model_dir}/images and points3D (.bin or .txt); drop --pipeline.datamanager.strict-init")
        name_to_id = {im.name: im_id for im_id, im in images.items()}
        # COLMAP names images by their path inside the image folder: a view name without its first folder.
        colmap_names = [Path(*Path(n).parts[1:]).as_posix() for n in self.image_names]
        initial_ids = {name_to_id[colmap_names[i]] for i in self.active if colmap_names[i] in name_to_id}
        tracks = [set(p.image_ids.tolist()) for p in points.values()]
        if not any(tracks):
            raise ActiveViewError(
                f"{model_dir}/points3D has no point tracks (which images see each point), which strict-init needs; "
                "use the full COLMAP model or drop --pipeline.datamanager.strict-init"
            )
        keep = torch.tensor([len(initial_ids & track) >= min_views for track in tracks])
        if keep.numel() != meta["points3D_xyz"].shape[0]:
            raise ActiveViewError("seed points and COLMAP tracks disagree; re-run without --pipeline.datamanager.strict-init")
        if not keep.any():
            raise ActiveViewError(
                f"strict-init kept no seed point: none of {model_dir}/points3D is seen by {min_views} of the "
                f"{len(self.active)} initial views; use more initial views or drop --pipeline.datamanager.strict-init"
            )
        for key in [k for k, v in meta.items() if k.startswith("points3D_") and torch.is_tensor(v) and v.shape[:1] == keep.shape]:
            meta[key] = meta[key][keep]
        CONSOLE.print(f"strict init: kept {int(keep.sum())} of {keep.numel()} seed points seen by >= {min_views} initial views")

    def sample_train_cameras(self) -> List[int]:
        """A shuffled pass over the active views (nerfstudio calls this whenever a pass is used up)."""
        if not hasattr(self, "active"):  # called by the parent constructor before the split exists
            return [0]
        order = torch.randperm(len(self.active), generator=self.generator).tolist()
        return [self.active[i] for i in order]

    def next_train(self, step: int):
        camera, data = super().next_train(step)
        index = camera.metadata["cam_idx"]
        assert index in self.active, f"training view {index} is not active"
        return camera, data

    # ---- state saved in checkpoints ------------------------------------------------------------------------

    def get_extra_state(self) -> Dict[str, Any]:
        # Plain Python types only, so checkpoints load with torch.load(weights_only=True).
        return {"version": 1, "image_names": list(self.image_names), "active": list(self.active), "history": self.history}

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        saved = state.get("image_names")
        # hpgs-ns 0.1 saved bare file names
        if saved != self.image_names and saved != [Path(n).name for n in self.image_names]:
            raise ActiveViewError(
                "checkpoint's active views belong to a different scene or split; pass the --data it was trained on"
            )
        self.active = [int(i) for i in state["active"]]
        self.history = list(state["history"])
        if saved != self.image_names:  # 0.1 names in the round log: the views' names now
            by_file = {Path(n).name: n for n in self.image_names}
            for record in self.history:
                record["chosen"] = [by_file[n] for n in record["chosen"]]
                record["scores"] = {by_file[n]: v for n, v in record.get("scores", {}).items()}
        self.train_unseen_cameras = self.sample_train_cameras()
