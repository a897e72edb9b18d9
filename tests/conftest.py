"""Shared fixtures: a tiny synthetic scene, a short in-process `hpgs` training run, the shared data folder."""

from __future__ import annotations

import os
import sys
import textwrap
import urllib.request
from pathlib import Path
from typing import Iterator

import pytest

REPO = Path(__file__).resolve().parent.parent


def shared_dir() -> Path:
    """`../shared` beside the checkout, or $HPGS_SHARED."""
    return Path(os.environ.get("HPGS_SHARED", REPO.parent / "shared"))


def require_shared(*parts: str) -> Path:
    path = shared_dir().joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data {path} not found (set HPGS_SHARED to the shared/ folder)")
    return path


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A 40-camera, 64x48 synthetic `ring` scene (35 training views, 5 test views)."""
    from hpgs_ns.scenes.synthetic import make_scene

    return make_scene(
        tmp_path_factory.mktemp("scenes") / "ring", layout="ring", num_cameras=40, width=64, height=48, num_points=1500, seed=0
    )


def short_config(scene: Path, out: Path, steps: int = 60, every: int = 20, rounds: int = 2, initial: int = 6, **options):
    """An `hpgs` trainer config scaled down for tests (CPU rasterizer, tensorboard, no viewer); `options` are
    `--pipeline.selection.*` or `--pipeline.datamanager.*` options by field name (a name neither has: TypeError)."""
    from hpgs_ns.method_config import hpgs_trainer_config

    cfg = hpgs_trainer_config(steps)
    cfg.data = scene
    cfg.pipeline.datamanager.data = scene
    cfg.output_dir = out
    cfg.experiment_name = "test"
    cfg.timestamp = "run"
    cfg.vis = "tensorboard"
    cfg.steps_per_save = steps
    cfg.steps_per_eval_image = 10 * steps
    cfg.steps_per_eval_all_images = 10 * steps
    cfg.logging.local_writer.enable = False
    cfg.pipeline.model.rasterizer = "cpu"
    cfg.pipeline.model.warmup_length = 20
    cfg.pipeline.model.refine_every = 20
    cfg.pipeline.model.num_downscales = 0  # full resolution from the start: short runs visibly improve
    cfg.pipeline.model.sh_degree_interval = 20
    d, selection = cfg.pipeline.datamanager, cfg.pipeline.selection
    d.num_initial_views, selection.select_every, selection.max_rounds = initial, every, rounds
    for key, value in options.items():  # the selection loop's options, or the datamanager's
        if not hasattr(selection, key) and not hasattr(d, key):
            raise TypeError(f"short_config: no selection or datamanager option {key!r}")
        setattr(selection if hasattr(selection, key) else d, key, value)
    return cfg


def model_trainer(scene: Path, out: Path, steps: int = 12, **model_options):
    """A set-up trainer of `steps` steps with no rounds and no densification in them (rows stay put), its
    `--pipeline.model.*` options set by field name: for tests of per-Gaussian model mechanisms."""
    cfg = short_config(scene, out, steps=steps, rounds=0)
    cfg.pipeline.model.warmup_length = 1000
    for key, value in model_options.items():
        setattr(cfg.pipeline.model, key, value)
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


@pytest.fixture(scope="session")
def light_preference_model(tmp_path_factory) -> Path:
    """A small preference model (alexnet at 64 px, seeded head) for tests of selection mechanics. The shipped
    default runs two trunks at 224 px (0.7 s a view on one CPU core), which would nearly double the suite's time;
    its own quality is checked on garden's human labels (test_preference.py)."""
    import torch

    from hpgs_ns.preference.model import PreferenceModel

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = PreferenceModel("alexnet", input_size=64)
        model.head.weight.data.normal_(0, 0.05)
    return model.save(tmp_path_factory.mktemp("light-model") / "light.pt")


@pytest.fixture(autouse=True)
def _light_default_model(request, monkeypatch):
    """In-process runs use the light model wherever they would load the default, except in tests marked
    `shipped_model` (those that check the default itself)."""
    if request.node.get_closest_marker("shipped_model") is None:
        path = request.getfixturevalue("light_preference_model")
        monkeypatch.setattr("hpgs_ns.selectors.preference_features.DEFAULT_MODEL", path)


def run_training(cfg):
    """Set up and train in-process, the way `ns-train` does; returns the trainer."""
    cfg.set_timestamp()
    cfg.save_config()
    trainer = cfg.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return trainer


def run_training_seeing(cfg, see):
    """`run_training`, recording `see(trainer, step)` before each iteration (after that step's callbacks: the round
    and the model's step callback). Returns (trainer, {step: what `see` returned})."""
    from nerfstudio.engine.trainer import Trainer

    seen = {}
    original = Trainer.train_iteration

    def spy(self, step):
        seen[step] = see(self, step)
        return original(self, step)

    Trainer.train_iteration = spy
    try:
        trainer = run_training(cfg)
    finally:
        Trainer.train_iteration = original
    return trainer, seen


def stock_ns_viewer_page(config: Path, env: dict) -> str:
    """Run stock `ns-viewer --load-config CONFIG` (nerfstudio's own entry point and tyro CLI, under `env`'s
    variables) and return the page its server serves once the viewer has loaded the checkpoint and built its scene.

    In-process: starting a second Python (imports, then the shipped preference model) took most of the time. Only
    the viewer's endless `while True: time.sleep(0.01)` is cut: its first sleep fetches the page and stops the
    viewer (and its viser server)."""
    import socket
    from unittest import mock

    from nerfstudio.scripts.viewer import run_viewer

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    made, page = [], []

    class Stop(Exception):
        pass

    def viewer_state(*args, **kwargs):
        made.append(real_state(*args, **kwargs))
        return made[-1]

    def first_sleep(_seconds):
        page.append(urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30).read().decode())
        raise Stop

    real_state = run_viewer.ViewerState
    argv = ["ns-viewer", "--load-config", str(config), "--viewer.websocket-port", str(port),
            "--viewer.websocket-host", "127.0.0.1"]
    try:
        with mock.patch.dict(os.environ, env, clear=True), mock.patch.object(sys, "argv", argv), \
                mock.patch.object(run_viewer, "ViewerState", viewer_state), \
                mock.patch.object(run_viewer, "time", mock.Mock(sleep=first_sleep)):
            run_viewer.entrypoint()
    except Stop:
        pass
    finally:
        for viewer in made:
            viewer.viser_server.stop()
    assert made and page and "<html" in page[0].lower(), "stock ns-viewer did not serve its page"
    return page[0]


CHROMIUM = "/usr/bin/chromium"


def playwright_or_skip():
    """playwright's `sync_playwright`; skips the test (naming what is missing) without playwright or Chromium."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright (pip) is not installed")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"{CHROMIUM} not found (apt-get install chromium)")
    return sync_playwright


# A third-party selector package (the plugin's and the lab's tests of entry-point selectors).
TOY = textwrap.dedent('''
    """A third-party selector: always the candidate with the highest index."""
    from dataclasses import dataclass, field
    from typing import Type

    from hpgs_ns.selectors.base import Selection, SelectorConfig


    class LastSelector:
        def __init__(self, config):
            self.config = config

        def select(self, context):
            picked = sorted(context.candidates)[-context.num_to_pick:]
            return Selection(indices=picked, scores={c: float(c) for c in context.candidates})


    @dataclass
    class LastSelectorConfig(SelectorConfig):
        """Always the candidates with the highest index."""

        _target: Type = field(default_factory=lambda: LastSelector)
        keep_last: int = 1
        """An option of a third-party selector (unused by its choice)."""
''')


@pytest.fixture
def toy_plugin(tmp_path, monkeypatch) -> Iterator[Path]:
    """An installed package `toy_selector` whose entry point registers the selector `last`."""
    (tmp_path / "toy_selector.py").write_text(TOY)
    info = tmp_path / "toy_selector-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-selector\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[hpgs_ns.selectors]\nlast = toy_selector:LastSelectorConfig\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    # an earlier test's copy, imported from its own folder, must not stand in for this one (nor outlive this test)
    monkeypatch.delitem(sys.modules, "toy_selector", raising=False)
    yield tmp_path
    sys.modules.pop("toy_selector", None)
