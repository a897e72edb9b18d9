"""The active datamanager: trains on a growing subset of the training views.

Built on nerfstudio's `FullImageDatamanager`. The training split is divided into *active* views (sampled for
training) and withheld *candidates*; the test split is neither, ever. The selection loop (`hpgs_ns.selection`)
decides when views join and which; this class owns the split, the sampling of training views, and the state that
checkpoints keep: the active set and the round records (`get_extra_state`), restored by `--load-dir`, `ns-eval`
and `ns-viewer`.

Views are named by their image's path relative to the data root (`hpgs_ns.dataparser.view_name`): Blender's
train and test splits both hold `r_0.png`. The test split is the dataparser's own; a test view is never active
and never a candidate, and a split with no test views (`--eval-mode all`) or test views that are also training
views is an error.

The selection loop's options live on the pipeline (`--pipeline.selection.*`); this config keeps their 0.2
spelling as deprecated aliases that the pipeline moves there.
"""

from __future__ import annotations

import copy
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple, Type

import numpy as np
import torch
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from hpgs_ns import compat
from hpgs_ns.dataparser import DataParserUnion, MipNerf360DataParserConfig, SceneDataError, check_image_sizes, view_name
from hpgs_ns.errors import UserError, check_option
from hpgs_ns.selection.records import RoundRecord
from hpgs_ns.selectors.farthest import farthest_point_order


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
    (e.g. an arc of the capture held back, to check what `hpgs suggest` says of it)."""
    initial_view_names: Tuple[str, ...] = ()
    """Explicit initial views by name (image path relative to the data root, e.g. `images/0001.png`, or just the
    file name where that is unambiguous); overrides initial-views."""
    seed: int = 0
    """Seeds the initial views (random/fps), the order views are trained in, and the selectors' randomness."""
    seed_points: Literal["auto", "colmap", "colmap-initial", "active", "random"] = "auto"
    """Where the splat's seed points come from. `auto`: `colmap` when the capture has a point cloud, else `active`
    (a capture without one, nerfstudio-data or Blender, would otherwise start from random points, which loses
    several dB: docs/active-training.md "Start modes"). `colmap`: the dataparser's points (a COLMAP model built
    from every photo, test and withheld ones included), or splatfacto's random points when it has none: what
    published tables used, and the default before `auto`. `colmap-initial`: only those COLMAP points whose track includes two initial
    views, so withheld and test views leak no geometry into the starting splat (needs a COLMAP model with point
    tracks). `active`: points triangulated from the initial views' photos alone at their known poses
    (`hpgs_ns.scenes.triangulate`), for any scene (COLMAP, nerfstudio-data, Blender: no tracks needed), and again
    after each round with the views it added (new points away from the splat join it as Gaussians); too few points
    -> random points, with one line naming the count. `random`: splatfacto's random points (as
    --pipeline.model.random-init True)."""
    seed_points_min: int = 100
    """`seed-points active`: fewer triangulated points than this and the splat starts from random points instead
    (one line naming the count), and a restart keeps its step-0 Gaussians. A few hundred accurate points seed a
    splat well; a handful, mostly from one pair of views, may not beat splatfacto's random start."""
    def __post_init__(self) -> None:
        # tyro builds this config while it parses the command line: a value that makes no sense is a one-line error
        # before nerfstudio prints the config or makes a run folder. (A config.yml is read without __init__.)
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()
        flag = "--pipeline.datamanager."
        check_option(flag + "num-initial-views", self.num_initial_views,
                     self.num_initial_views >= 1 or bool(self.initial_view_names), "must be at least 1",
                     "pass 1 or more (or name the views: --pipeline.datamanager.initial-view-names)")
        check_option(flag + "camera-res-scale-factor", self.camera_res_scale_factor, self.camera_res_scale_factor > 0,
                     "must be > 0", "pass e.g. 0.5 for half resolution, or 1")
        check_option(flag + "max-thread-workers", self.max_thread_workers,
                     self.max_thread_workers is None or self.max_thread_workers >= 1, "must be at least 1",
                     "pass 1 or more, or leave it out (all the CPU's threads)")

    def __setstate__(self, state: dict) -> None:
        # A config.yml saved before an option group existed (PyYAML restores attributes, not __init__) gets that
        # group's defaults; plain-valued options already fall back to their class defaults.
        self.__dict__.update(state)
        compat.read_datamanager_state(self)
        for f in fields(self):
            if f.name not in self.__dict__ and f.default_factory is not MISSING:
                setattr(self, f.name, f.default_factory())


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
        load_points = getattr(config.dataparser, "load_3D_points", None)
        if config.seed_points in ("active", "random") and load_points:
            # these modes drop the capture's points anyway: not reading them also spares the dataparser's
            # "no seed points: random start" line, which is wrong for `active` (restored below: the config is the user's)
            config.dataparser.load_3D_points = False
        try:
            super().__init__(config, device=device, test_mode=test_mode, **kwargs)
        except AssertionError as err:  # nerfstudio checks each image's size against its camera's while caching
            if "does not match the camera parameters" not in str(err):
                raise
            raise SceneDataError(
                f"{err}: the images were downscaled with another rounding than the cameras; pass the dataparser's "
                "--downscale-rounding-mode (floor, round or ceil) that made them, or delete the images_N folder"
            ) from None
        finally:
            if load_points is not None:
                config.dataparser.load_3D_points = load_points
        if test_mode != "inference":  # nerfstudio loads the photos lazily, and asserts their size mid-run
            check_image_sizes([self.train_dataset, self.eval_dataset], self.config.dataparser)
        # The cameras as the photos on disk were taken. nerfstudio's image cache (filled at the first training step)
        # undistorts the images and rewrites the dataset's intrinsics and sizes in place, keeping the distortion
        # coefficients: what reads the photos from disk later (a round's triangulation, random-points views at a
        # restart) needs these.
        self.photo_cameras = copy.deepcopy(self.train_dataset.cameras)
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
        self.history: List[RoundRecord] = []
        self.selection_signature: Optional[Dict[str, str]] = None
        """The run's selection options as the checkpoint keeps them (set by the pipeline; see `HpgsTrainer`)."""
        self.loaded_selection_signature: Optional[Dict[str, str]] = None
        """The checkpoint's, once one is loaded (None for checkpoints written before 0.3)."""
        self.triangulation: Optional[Any] = None
        """The `TriangulationWorkspace` of `seed-points active` (features and matches of the views seen so far)."""
        self.seed_points_mode = self._seed_points_mode()
        points = self.train_dataparser_outputs.metadata.get("points3D_xyz")
        has_points = points is not None and len(points) > 0
        if self.seed_points_mode == "auto":
            self.seed_points_mode = "colmap" if has_points else "active"
            if not has_points and test_mode == "val":
                CONSOLE.print("seed points: the capture has no point cloud, so they are triangulated from the active views "
                              "(--pipeline.datamanager.seed-points auto; `colmap` keeps splatfacto's random start)",
                              soft_wrap=True, highlight=False)
        elif self.seed_points_mode == "colmap" and not has_points and test_mode == "val":
            CONSOLE.print("seed points: the capture has no point cloud, so the splat starts from random points "
                          "(--pipeline.datamanager.seed-points auto triangulates the active views instead)",
                          soft_wrap=True, highlight=False)
        if self.seed_points_mode == "active" and test_mode == "val":  # training triangulates: at the start, each round, restarts
            from hpgs_ns.scenes.triangulate import require_pycolmap

            auto = self.config.seed_points == "auto"
            require_pycolmap(f"--pipeline.datamanager.seed-points {'auto on a capture without a point cloud' if auto else 'active'}"
                             " (it triangulates the active views)",
                             "or --pipeline.datamanager.seed-points colmap" + (" for splatfacto's random start" if auto else ""))
        self._colmap_xyz: Optional[torch.Tensor] = None
        """The capture's COLMAP points, all of them (before `colmap-initial` filters the seed points), in the
        dataparser's frame: what `active_views` cuts to the active views' tracks."""
        if self.seed_points_mode in ("colmap", "colmap-initial") and has_points and hasattr(self.config.dataparser, "colmap_path"):
            self._colmap_xyz = points.clone()
        self._colmap_observers: Optional[torch.Tensor] = None
        if self.seed_points_mode == "colmap-initial":
            self._keep_points_seen_by_initial_views()
        elif self.seed_points_mode == "random":
            self._drop_seed_points()
        elif self.seed_points_mode == "active" and test_mode == "val":  # training; ns-eval/ns-viewer ("test") load the checkpoint's
            if getattr(self.config, "start_from_checkpoint", False):
                self._drop_seed_points()  # a resume: the checkpoint replaces the splat and says how it started
            else:
                self._triangulate_seed_points()
        self.train_unseen_cameras = self.sample_train_cameras()

    # ---- which views are active ----------------------------------------------------------------------------

    @property
    def candidates(self) -> List[int]:
        """Withheld training views, in index order."""
        active = set(self.active) | getattr(self, "excluded", set())
        return [i for i in range(len(self.train_dataset)) if i not in active]

    @property
    def active_cameras(self):
        """The active views' cameras (`Cameras` [len(active)]), in `active`'s order."""
        return self.train_dataset.cameras[torch.tensor(self.active, dtype=torch.long)]

    @property
    def initial_views(self) -> List[int]:
        """Active views that no round added."""
        added = {i for h in self.history for i in h.chosen_indices}
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
                raise ActiveViewError(
                    f"initial view {self.image_names[min(self.excluded & set(chosen))]!r} is also excluded; drop it from one list"
                )
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

    # ---- seed points (`--pipeline.datamanager.seed-points`) ------------------------------------------------

    def _seed_points_mode(self) -> str:
        """`seed-points` as given (`auto` is resolved by the caller, once it knows whether the capture has points)."""
        mode = self.config.seed_points
        if mode in ("active", "auto") and self.config.seed_points_min < 1:
            raise ActiveViewError(f"--pipeline.datamanager.seed-points-min {self.config.seed_points_min}: the fewest "
                                  "triangulated points to start from must be at least 1")
        return mode

    def _drop_seed_points(self) -> None:
        """No seed points: splatfacto then starts from its random points (as --pipeline.model.random-init True)."""
        meta = self.train_dataparser_outputs.metadata
        for key in [k for k in meta if k.startswith("points3D_")]:
            del meta[key]

    def _triangulate_seed_points(self) -> None:
        """`seed-points active`: the seed points triangulated from the initial views' photos alone; random points
        (one line naming the count) when too few."""
        from hpgs_ns.scenes.triangulate import seed_points

        self._drop_seed_points()  # the dataparser's points (every photo's) never reach the model
        points = seed_points(self.photo_cameras, self.train_dataset.image_filenames, self.active,
                             existing=self.triangulation_workspace(), min_points=self.config.seed_points_min)
        if points is None:
            return
        meta = self.train_dataparser_outputs.metadata
        meta["points3D_xyz"], meta["points3D_rgb"] = points
        CONSOLE.print(f"seed points: {points[0].shape[0]} triangulated from the {len(self.active)} initial views")

    def triangulation_workspace(self):
        """The run's `TriangulationWorkspace`, made on first use and removed when the datamanager goes (or at exit).
        A resumed run makes a new one: its first round extracts every active view again."""
        if self.triangulation is None:
            import weakref

            from hpgs_ns.scenes.triangulate import TriangulationWorkspace

            self.triangulation = TriangulationWorkspace()
            weakref.finalize(self, self.triangulation.close)
        return self.triangulation

    def triangulate_active(self):
        """`triangulate_views` over the active views now, reusing the workspace: (xyz [N, 3], rgb [N, 3], info)."""
        from hpgs_ns.scenes.triangulate import triangulate_views

        return triangulate_views(self.photo_cameras, self.train_dataset.image_filenames, self.active,
                                 existing=self.triangulation_workspace(), min_points=self.config.seed_points_min)

    def _keep_points_seen_by_initial_views(self, min_views: int = 2) -> None:
        """Filter the dataparser's seed points in place (the pipeline hands them to the model after this)."""
        # nerfstudio's own COLMAP reader, as its dataparser used: the mask then lines up with its point order.
        from hpgs_ns.scenes.colmap_model import read_images, read_points3D

        parser = self.config.dataparser
        # `active` needs no tracks
        name, drop = "seed-points colmap-initial", "use --pipeline.datamanager.seed-points active (or colmap)"
        if not hasattr(parser, "colmap_path"):
            raise ActiveViewError(
                f"{name} needs COLMAP point tracks (which images see each point), which only COLMAP scenes have "
                f"(the mipnerf360 or colmap dataparser); {drop}"
            )
        meta = self.train_dataparser_outputs.metadata
        if "points3D_xyz" not in meta:
            return
        model_dir = Path(parser.data) / parser.colmap_path
        images, points = read_images(model_dir), read_points3D(model_dir)
        if images is None or points is None:
            raise ActiveViewError(
                f"{name} needs {model_dir}/images and points3D (.bin or .txt); {drop}"
            )
        name_to_id = {im.name: im_id for im_id, im in images.items()}
        # COLMAP names images by their path inside the image folder: a view name without its first folder.
        colmap_names = [Path(*Path(n).parts[1:]).as_posix() for n in self.image_names]
        initial_ids = {name_to_id[colmap_names[i]] for i in self.active if colmap_names[i] in name_to_id}
        tracks = [set(p.image_ids.tolist()) for p in points.values()]
        if not any(tracks):
            raise ActiveViewError(
                f"{model_dir}/points3D has no point tracks (which images see each point), which {name} needs; "
                f"use the full COLMAP model or {drop}"
            )
        keep = torch.tensor([len(initial_ids & track) >= min_views for track in tracks])
        if keep.numel() != meta["points3D_xyz"].shape[0]:
            raise ActiveViewError(f"seed points and COLMAP tracks disagree; {drop}")
        if not keep.any():
            raise ActiveViewError(
                f"{name} kept no seed point: none of {model_dir}/points3D is seen by {min_views} of the "
                f"{len(self.active)} initial views; use more initial views or {drop}"
            )
        for key in [k for k, v in meta.items() if k.startswith("points3D_") and torch.is_tensor(v) and v.shape[:1] == keep.shape]:
            meta[key] = meta[key][keep]
        CONSOLE.print(f"seed-points colmap-initial: kept {int(keep.sum())} of {keep.numel()} seed points seen by >= "
                      f"{min_views} initial views")

    # ---- what the trainer strategies see (`hpgs_ns.strategies`) -------------------------------------------------

    def active_views(self):
        """The active views and the sparse points they see (`strategies.base.ActiveViews`): the COLMAP model's points
        (seed-points colmap or colmap-initial) or the `active` start's last triangulation (of active views only),
        each with its track cut to the active views; a point no active view sees is left out, so one only withheld
        or test views see never reaches a strategy."""
        from hpgs_ns.strategies.base import ActiveViews, TrackedPoints

        active = list(self.active)
        found = self._tracked_points()
        if isinstance(found, str):
            return ActiveViews(active, None, found)
        xyz, observers, source = found
        is_active = torch.zeros(observers.shape[1], dtype=torch.bool)
        is_active[torch.tensor(active, dtype=torch.long)] = True
        observers = observers & is_active
        seen = observers.any(1)
        return ActiveViews(active, TrackedPoints(xyz[seen], observers[seen], source))

    def _tracked_points(self):
        """(xyz [P, 3], observers [P, V] bool over the training split, source) of every sparse point with a track,
        or one clause saying why the run has none."""
        views = len(self.image_names)
        if self.seed_points_mode == "active":
            last = getattr(self.triangulation, "last_points", None)
            if last is None:
                return "seed-points active has triangulated no points yet (a resumed run does at its next round)"
            xyz, tracks = last
            observers = torch.zeros((len(tracks), views), dtype=torch.bool)
            for row, track in enumerate(tracks):
                observers[row, torch.tensor(track, dtype=torch.long)] = True
            return torch.from_numpy(xyz).float(), observers, "the active views' triangulation"
        if self._colmap_xyz is None:
            if self.seed_points_mode == "random":
                return "seed-points random drops the capture's points (COLMAP tracks or seed-points active supply them)"
            return ("the capture has no COLMAP model with point tracks (--pipeline.datamanager.seed-points active "
                    "triangulates the active views)")
        if self._colmap_observers is None:
            from hpgs_ns.scenes.colmap_model import read_images, read_points3D

            parser = self.config.dataparser
            model_dir = Path(parser.data) / parser.colmap_path
            images, points = read_images(model_dir), read_points3D(model_dir)
            if images is None or points is None or len(points) != self._colmap_xyz.shape[0]:
                return f"{model_dir} has no point tracks that line up with the capture's points"
            colmap_names = [Path(*Path(n).parts[1:]).as_posix() for n in self.image_names]
            view_of = {im_id: colmap_names.index(im.name) for im_id, im in images.items() if im.name in colmap_names}
            observers = torch.zeros((len(points), views), dtype=torch.bool)
            for row, point in enumerate(points.values()):
                track = [view_of[i] for i in point.image_ids.tolist() if i in view_of]
                observers[row, torch.tensor(track, dtype=torch.long)] = True
            self._colmap_observers = observers
        return self._colmap_xyz, self._colmap_observers, "the COLMAP tracks"

    def sample_train_cameras(self) -> List[int]:
        """A shuffled pass over the active views, each once (nerfstudio calls this whenever a pass is used up; an add
        starts a new one)."""
        if not hasattr(self, "active"):  # called by the parent constructor before the split exists
            return [0]
        views = list(self.active)
        order = torch.randperm(len(views), generator=self.generator).tolist()
        return [views[i] for i in order]

    def next_train(self, step: int):
        camera, data = super().next_train(step)
        index = camera.metadata["cam_idx"]
        assert index in self.active, f"training view {index} is not active"
        return camera, data

    # ---- state saved in checkpoints ------------------------------------------------------------------------

    def get_extra_state(self) -> Dict[str, Any]:
        # Plain Python types only, so checkpoints load with torch.load(weights_only=True).
        state = {"version": 1, "image_names": list(self.image_names), "active": list(self.active),
                 "history": [record.to_dict() for record in self.history]}
        if self.selection_signature:
            state["selection"] = dict(self.selection_signature)
        # Where the shuffled pass over the active views stands: a resumed run visits them in the same order.
        state["train_unseen"] = [int(i) for i in self.train_unseen_cameras]
        state["generator"] = self.generator.get_state()
        return state

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        renamed = compat.view_names_now(state.get("image_names"), self.image_names)
        if renamed is None:
            raise ActiveViewError(
                "checkpoint's active views belong to a different scene or split; pass the --data it was trained on"
            )
        self.active = [int(i) for i in state["active"]]
        self.history = [RoundRecord.from_dict(record) for record in state["history"]]
        self.loaded_selection_signature = state.get("selection")
        for record in self.history if renamed else []:  # the round log in the views' names now
            record.chosen = [renamed[n] for n in record.chosen]
            record.scores = {renamed[n]: v for n, v in record.scores.items()}
        if "generator" in state:
            self.generator.set_state(state["generator"])
        unseen = [int(i) for i in state.get("train_unseen", [])]
        self.train_unseen_cameras = unseen if unseen and set(unseen) <= set(self.active) else self.sample_train_cameras()
