"""`hpgs suggest --load-config RUN/config.yml`: the next photos to take, scored by a selector on the trained splat.

The run is any `ns-train hpgs` run, or a stock `ns-train splatfacto` run (loaded into the plugin's model class, so
it renders on the CPU too). Candidate poses (`candidates`) are filtered (inside the object, view blocked close by,
too close to a photo already taken) and scored like withheld views: the selector sees the views the splat was
trained on as the active set and the candidates as the pool, and picks `--num` greedily (each pick joins the active
side before the next). Written into the run folder: `suggested_views.json` (poses in the scene's original
coordinates and in nerfstudio's), `suggested_camera_path.json` (nerfstudio's camera-path format: `ns-render
camera-path` and the viewer's render panel open it), `suggestions_contact_sheet.png` and `suggestions_map.png`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Dict, List, Optional, Tuple

from rich.console import Console

from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.errors import UserError

if TYPE_CHECKING:  # torch and nerfstudio are imported where used: `hpgs suggest --help` imports this module
    import torch

    from hpgs_ns.suggest import candidates as cand

CONSOLE = Console(stderr=True)


class SuggestError(UserError, ValueError):
    """The run cannot be loaded or suggested for."""


@dataclass
class Suggest:
    """Suggest where to take the next photos of a capture, from a trained run."""

    load_config: Path
    """The run's config.yml (`ns-train hpgs` or `ns-train splatfacto`)."""
    num: int = 5
    """How many poses to suggest (greedy: each pick counts as taken for the next)."""
    selector: Optional[str] = None
    """The selector that scores them (default: the run's own, `ns-train hpgs`'s default, `farthest`, for a splatfacto run)."""
    candidates: str = "orbit"
    """`orbit` (rings at the captured cameras' heights and radii, looking at the centre), `sphere` (a Fibonacci
    sphere at their distance), or a JSON file (a nerfstudio camera path, or a list of camera-to-world matrices)."""
    count: int = 128
    """Sphere points, or orbit poses in all (3 rings)."""
    min_distance: float = 1.0
    """Drop candidates closer to a photo already taken than this many times the usual spacing between photos."""
    clearance: float = 0.3
    """Drop candidates whose view is blocked nearer than this fraction of their distance to the scene centre."""
    seed: int = 0
    """Seeds the selector's randomness."""

    def main(self) -> None:
        run = load_run(self.load_config)
        out = suggest(run, self)
        CONSOLE.print(f"{len(out['suggestions'])} suggestions -> {self.load_config.parent / 'suggested_views.json'}")
        for s in out["suggestions"]:
            p = s["position_original"]
            print(f"{s['rank']}. score {s['score']:.4g}  at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) in the scene's coordinates")


@dataclass
class Run:
    """A loaded run: the pipeline and what the suggestions need of it."""

    config: object
    pipeline: object
    run_dir: Path
    trained: List[int]
    """Training-split views the splat was trained on (all of them for a splatfacto run)."""
    names: List[str]
    selector: str


def load_run(config_path: Path) -> Run:
    """The run's pipeline (stock splatfacto's model swapped for the plugin's), on the GPU if there is one."""
    from nerfstudio.models.splatfacto import SplatfactoModelConfig
    from nerfstudio.utils.eval_utils import eval_setup

    from hpgs_ns.dataparser import view_name
    from hpgs_ns.model import HpgsSplatfactoModelConfig
    from hpgs_ns.run_config import RunConfigError, read_run_config
    from hpgs_ns.selectors.registry import DEFAULT_SELECTOR

    config_path = Path(config_path)
    try:
        config = read_run_config(config_path)
    except RunConfigError as err:
        raise SuggestError(str(err)) from None
    checkpoints = config_path.parent / "nerfstudio_models"
    if not checkpoints.is_dir() or not list(checkpoints.glob("step-*.ckpt")):
        raise SuggestError(f"{config_path.parent} has no checkpoint (nerfstudio_models/step-*.ckpt); train the run first")

    def to_plugin(cfg):
        model = cfg.pipeline.model
        if type(model) is SplatfactoModelConfig:  # stock splatfacto: same parameters, our rasterizer choice
            cfg.pipeline.model = HpgsSplatfactoModelConfig(**{f.name: getattr(model, f.name) for f in fields(SplatfactoModelConfig)})
        elif not isinstance(model, HpgsSplatfactoModelConfig):
            raise SuggestError(f"{config_path}: a {type(model).__name__} run; hpgs suggest needs a splatfacto or hpgs run")
        cfg.output_dir = config_path.parent.parent.parent.parent  # wherever the run folder is now
        cfg.experiment_name, cfg.method_name, cfg.timestamp = (
            config_path.parent.parent.parent.name, config_path.parent.parent.name, config_path.parent.name)
        return cfg

    try:
        config, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=to_plugin)
    except UserError:
        raise
    except Exception:
        # nerfstudio loads the newest checkpoint by name: one that does not load is named here, else the traceback
        from hpgs_ns.trainer import CheckpointError, checkpoint_step, load_checkpoint_file

        newest = max(checkpoints.glob("step-*.ckpt"), key=checkpoint_step)
        try:
            load_checkpoint_file(newest)
        except CheckpointError as err:
            raise SuggestError(f"{err}; move it out of {checkpoints} to use the one before it") from None
        raise
    dm = pipeline.datamanager
    root = Path(dm.config.dataparser.data)
    names = list(getattr(dm, "image_names", None) or [view_name(p, root) for p in dm.train_dataset.image_filenames])
    trained = sorted(getattr(dm, "active", range(len(dm.train_dataset))))
    selection = getattr(config.pipeline, "selection", None)  # an hpgs run's selection options (None: splatfacto)
    return Run(config, pipeline, config_path.parent, list(trained), names,
               selection.selector if selection else DEFAULT_SELECTOR)


def candidate_poses(run: Run, args: Suggest) -> Tuple[torch.Tensor, List[float], cand.Layout]:
    from hpgs_ns.suggest import candidates as cand

    captured = run.pipeline.datamanager.train_dataset.cameras.camera_to_worlds
    lay = cand.layout(captured)
    if args.candidates == "orbit":
        return cand.orbit(lay, rings=3, per_ring=max(args.count // 3, 4)), [], lay
    if args.candidates == "sphere":
        return cand.sphere(lay, args.count), [], lay
    poses, fovs = cand.from_file(Path(args.candidates))
    return poses, fovs, lay


def candidate_cameras(run: Run, c2w: torch.Tensor, fovs: List[float]):
    """Cameras at `c2w` with the captured cameras' intrinsics (a camera path's own field of view where given)."""
    import torch
    from nerfstudio.cameras.cameras import Cameras, CameraType

    cams = run.pipeline.datamanager.train_dataset.cameras
    fx, fy = float(cams.fx.median()), float(cams.fy.median())
    w, h = int(cams.width[0]), int(cams.height[0])
    fy_each = torch.full((len(c2w), 1), fy)
    for i, fov in enumerate(fovs):
        if not math.isnan(fov):
            fy_each[i] = h / (2 * math.tan(math.radians(fov) / 2))
    return Cameras(camera_to_worlds=c2w.float(), fx=fy_each * fx / fy, fy=fy_each, cx=w / 2.0, cy=h / 2.0, width=w, height=h,
                   camera_type=CameraType.PERSPECTIVE)


def blocked(model, cameras, lay: cand.Layout, clearance: float, short_side: int = 48) -> torch.Tensor:
    """[N] bool: the splat's depth in the middle of the view is nearer than `clearance` x the distance to the
    centre (inside geometry, or behind a wall)."""
    import torch

    out = []
    small = copy.deepcopy(cameras)
    small.rescale_output_resolution(short_side / float(min(int(cameras.width[0]), int(cameras.height[0]))))
    with torch.no_grad(), model.eval_mode():
        for i in range(small.shape[0]):
            result = model.get_outputs_for_camera(small[i : i + 1].to(model.device))
            depth, alpha = result["depth"][..., 0], result["accumulation"][..., 0]
            h, w = depth.shape
            middle = (slice(h // 4, h - h // 4), slice(w // 4, w - w // 4))
            d = depth[middle][alpha[middle] > 0.5]
            distance = float((cameras.camera_to_worlds[i, :3, 3] - lay.centre).norm())
            out.append(bool(d.numel() > 0.5 * alpha[middle].numel()) and float(d.median()) < clearance * distance)
    return torch.tensor(out, dtype=torch.bool)


def suggest(run: Run, args: Suggest) -> Dict:
    """Generate, filter and score candidate poses; write the files; return what suggested_views.json holds."""
    import torch

    from hpgs_ns.selectors.base import SelectionContext, check_selection
    from hpgs_ns.selectors.registry import selector_config
    from hpgs_ns.suggest import candidates as cand

    if args.num < 1:
        raise SuggestError("--num must be at least 1")
    dm, model = run.pipeline.datamanager, run.pipeline.model
    poses, fovs, lay = candidate_poses(run, args)
    captured = torch.cat([dm.train_dataset.cameras.camera_to_worlds, dm.eval_dataset.cameras.camera_to_worlds])
    close = cand.too_close(poses, captured, args.min_distance * lay.spacing)
    inside = cand.inside_object(poses, model.means.detach().cpu(), torch.sigmoid(model.opacities.detach().cpu()).squeeze(-1), lay)
    keep = ~(close | inside)
    cameras = candidate_cameras(run, poses, fovs)
    block = torch.zeros(len(poses), dtype=torch.bool)
    if keep.any():
        block[keep] = blocked(model, cameras[keep.nonzero()[:, 0]], lay, args.clearance)
    keep &= ~block
    dropped = cand.counts(too_close=close, inside_object=inside & ~close, view_blocked=block)
    if not keep.any():
        raise SuggestError(
            f"no candidate pose left: of {len(poses)} {args.candidates} poses, {dropped['too_close']} are within "
            f"{args.min_distance:g} x the photo spacing of a photo, {dropped['inside_object']} inside the object, "
            f"{dropped['view_blocked']} blocked nearer than {args.clearance:g} x their distance; lower --min-distance "
            "or --clearance, or try --candidates sphere"
        )
    pool = keep.nonzero()[:, 0].tolist()
    trained = dm.train_dataset.cameras[torch.tensor(run.trained, dtype=torch.long)]
    # trained views first, then the candidates: one index space for the selector
    combined = _concat(trained, cameras[torch.tensor(pool, dtype=torch.long)])
    n = len(run.trained)
    name = args.selector or run.selector
    selection = getattr(run.config.pipeline, "selection", None)
    selector = (selection.selector_config(name) if selection is not None else selector_config(name)).setup()
    context = SelectionContext(
        step=int(getattr(model, "step", 0)), round_index=0, active=list(range(n)),
        candidates=list(range(n, n + len(pool))), num_to_pick=min(args.num, len(pool)), cameras=combined,
        image_names=[run.names[i] for i in run.trained] + [f"candidate-{i:04d}" for i in pool], model=model,
        render=lambda idx, short=None: model.render_views(combined[torch.tensor([int(i) for i in idx], dtype=torch.long)], short),
        generator=torch.Generator().manual_seed(args.seed), device=torch.device(model.device),
    )
    selection = check_selection(selector.select(context), context)
    picked = [pool[i - n] for i in selection.indices]
    scores = {pool[i - n]: s for i, s in selection.scores.items()}
    return write_outputs(run, args, poses, cameras, picked, scores, pool, dropped, lay, name)


def _concat(a, b):
    """Two Cameras of one kind in one (nerfstudio's Cameras has no concatenation)."""
    import torch
    from nerfstudio.cameras.cameras import Cameras

    cat = lambda x, y: torch.cat([x.reshape(len(x), -1), y.reshape(len(y), -1)])  # noqa: E731
    return Cameras(
        camera_to_worlds=torch.cat([a.camera_to_worlds, b.camera_to_worlds]), fx=cat(a.fx, b.fx), fy=cat(a.fy, b.fy),
        cx=cat(a.cx, b.cx), cy=cat(a.cy, b.cy), width=cat(a.width, b.width), height=cat(a.height, b.height),
        camera_type=cat(a.camera_type, b.camera_type),
    )


def write_outputs(run: Run, args: Suggest, poses, cameras, picked, scores, pool, dropped, lay, name: str) -> Dict:
    import torch

    from hpgs_ns.suggest.figures import contact_sheet, top_down_map

    dm = run.pipeline.datamanager
    outputs = dm.train_dataparser_outputs
    convention = "opencv" if hasattr(dm.config.dataparser, "colmap_path") else "opengl"
    chosen = torch.tensor(picked, dtype=torch.long)
    original = outputs.transform_poses_to_original_space(poses[chosen].float(), camera_convention=convention)
    h, w = int(cameras.height[0]), int(cameras.width[0])
    fov = [math.degrees(2 * math.atan(h / (2 * float(cameras.fy[i])))) for i in picked]
    suggestions = []
    for rank, (i, orig) in enumerate(zip(picked, original), 1):
        suggestions.append({
            "rank": rank, "score": float(scores.get(i, float("nan"))), "candidate": int(i),
            "position_original": orig[:3, 3].tolist(),
            "camera_to_world_original": torch.cat([orig, torch.tensor([[0, 0, 0, 1.0]])]).tolist(),
            "camera_to_world": torch.cat([poses[i], torch.tensor([[0, 0, 0, 1.0]])]).tolist(),
            "fov_deg": fov[rank - 1], "width": w, "height": h,
        })
    path = {
        "camera_type": "perspective", "render_height": h, "render_width": w, "fps": 1, "seconds": len(picked),
        "default_fov": fov[0], "default_transition_sec": 1.0, "is_cycle": False, "smoothness_value": 0.0,
        "keyframes": [{"matrix": sum(s["camera_to_world"], []), "fov": s["fov_deg"], "aspect": w / h} for s in suggestions],
        "camera_path": [{"camera_to_world": sum(s["camera_to_world"], []), "fov": s["fov_deg"], "aspect": w / h} for s in suggestions],
    }
    payload = {
        "selector": name, "num": len(picked), "candidates": args.candidates, "generated": len(poses), "scored": len(pool),
        "dropped": dropped, "min_distance": args.min_distance * lay.spacing, "clearance": args.clearance,
        "trained_views": len(run.trained),
        "coordinates": f"camera_to_world_original: the scene's own coordinates ({convention} cameras), the dataparser's "
                       "transform undone; camera_to_world: nerfstudio's (what the viewer and ns-render use)",
        "suggestions": suggestions, "camera_path": path,
    }
    write_json_atomic(run.run_dir / "suggested_views.json", payload)
    write_json_atomic(run.run_dir / "suggested_camera_path.json", path)
    renders = run.pipeline.model.render_views(cameras[chosen], short_side=min(h, w, 256))
    contact_sheet(renders, [s["score"] for s in suggestions], name, run.run_dir / "suggestions_contact_sheet.png")
    top_down_map(dm, poses, pool, picked, lay, run.run_dir / "suggestions_map.png")
    return payload
