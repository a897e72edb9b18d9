"""The selection in nerfstudio's viewer (`hpgs_ns.viewer`): a short CPU run with two rounds, opened the way
`ns-viewer --load-config` opens it, shown in headless Chromium; and the same view updated live by the rounds of a
run trained with the viewer on.

What the scene holds is read back from viser's server side: the messages it keeps for every new client.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
from conftest import CHROMIUM, playwright_or_skip, run_training, short_config
from PIL import Image

WIDTH, HEIGHT = 1024, 680  # software GL renders every frame on the CPU: a small page keeps the test fast


def _config(scene: Path, out: Path):
    """30 steps, rounds at 10 and 20 adding two views each (farthest: no weights to load)."""
    return short_config(scene, out, steps=30, every=10, rounds=2, initial=6, selector="farthest", views_per_round=2)


@pytest.fixture(scope="module")
def run_config(tiny_scene, tmp_path_factory) -> Path:
    cfg = _config(tiny_scene, tmp_path_factory.mktemp("runs"))
    run_training(cfg)
    return cfg.get_base_dir() / "config.yml"


def open_viewer(config_path: Path):
    """What `ns-viewer --load-config` does (nerfstudio.scripts.viewer.run_viewer), without its endless loop."""
    from nerfstudio.utils.eval_utils import eval_setup
    from nerfstudio.viewer.viewer import Viewer
    from nerfstudio.viewer_legacy.server.viewer_utils import get_free_port

    config, pipeline, _, step = eval_setup(config_path, test_mode="test")
    config.viewer.websocket_host = "127.0.0.1"
    config.viewer.websocket_port = get_free_port()
    # `--viewer.default-composite-depth False`: a 30-step splat is haze everywhere and would hide the cameras.
    config.viewer.default_composite_depth = False
    viewer = Viewer(
        config.viewer,
        log_filename=config.get_base_dir() / config.viewer.relative_log_filename,
        datapath=pipeline.datamanager.get_datapath(),
        pipeline=pipeline,
        train_lock=threading.Lock(),
    )
    dm = pipeline.datamanager
    viewer.init_scene(train_dataset=dm.train_dataset, train_state="completed", eval_dataset=dm.eval_dataset)
    viewer.update_scene(step=step)
    return viewer, pipeline


def scene_nodes(server) -> Dict[str, object]:
    """Scene node name -> the message that made it, replaying what viser sends a client that connects now."""
    from viser import _messages

    ws = server._websock_server
    # Messages sent inside `server.atomic()` reach the buffer later, from viser's thread pool, in order.
    deadline = time.time() + 10
    while not ws._queued_messages.empty() and time.time() < deadline:
        time.sleep(0.01)
    with ws._atomic_lock:
        pass
    buffer = ws._broadcast_buffer
    with buffer.buffer_lock:
        messages = [buffer.message_from_id[i] for i in sorted(buffer.message_from_id)]
    nodes: Dict[str, object] = {}
    for m in messages:
        if isinstance(m, _messages.RemoveSceneNodeMessage):
            for name in [n for n in nodes if n == m.name or n.startswith(m.name + "/")]:
                del nodes[name]
        elif isinstance(m, (_messages.CameraFrustumMessage, _messages.LabelMessage, _messages.FrameMessage)):
            nodes[m.name] = m
    return nodes


def frustum_colours(server, prefix: str = "/hpgs/") -> Dict[str, int]:
    from viser import _messages

    return {n: m.color for n, m in scene_nodes(server).items() if isinstance(m, _messages.CameraFrustumMessage) and n.startswith(prefix)}


def rgb_int(rgb) -> int:
    return (rgb[0] << 16) | (rgb[1] << 8) | rgb[2]


def expected_roles(dm) -> Dict[str, str]:
    """Node name -> role from the datamanager's own lists (independently of hpgs_ns.viewer.camera_roles)."""
    added = {i for h in dm.history for i in h.chosen_indices}
    roles = {}
    for i in range(len(dm.image_names)):
        role = "added" if i in added else "initial" if i in dm.active else "withheld"
        roles[f"/hpgs/{role}/train_{i:04d}"] = role
    for j in range(len(dm.test_view_names)):
        roles[f"/hpgs/test/test_{j:04d}"] = "test"
    return roles


def look_at_all_cameras(viewer, pipeline) -> None:
    """Point every connected browser at the cameras from above and behind, so all roles are in view."""
    from hpgs_ns.viewer import VISER_SCALE

    cams = pipeline.datamanager.train_dataset.cameras.camera_to_worlds[:, :3, 3].numpy() * VISER_SCALE
    centre, radius = cams.mean(0), float(np.linalg.norm(cams - cams.mean(0), axis=1).max())
    for client in viewer.viser_server.get_clients().values():
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.position = tuple(centre + np.array([0.0, -1.6 * radius, 1.5 * radius]))
        client.camera.look_at = tuple(centre)


@pytest.fixture(scope="module")
def sync_playwright():
    """playwright's entry point; skips (before any training) without playwright or Chromium."""
    return playwright_or_skip()


def test_ns_viewer_shows_the_roles_and_the_rounds(sync_playwright, run_config, tmp_path):
    from hpgs_ns.viewer import ROLE_COLOURS, SelectionView

    viewer, pipeline = open_viewer(run_config)
    server, dm = viewer.viser_server, pipeline.datamanager
    view = pipeline.selection_view
    assert isinstance(view, SelectionView) and view.server is server
    assert len(dm.history) == 2

    # Every camera drawn once, in its role's colour; round labels on the added ones.
    colours = frustum_colours(server)
    roles = expected_roles(dm)
    assert {n: c for n, c in colours.items() if not n.startswith("/hpgs/highlight/")} == {
        n: rgb_int(ROLE_COLOURS[r]) for n, r in roles.items()
    }
    assert sum(r == "added" for r in roles.values()) == 4 and sum(r == "test" for r in roles.values()) == 5
    labels = {n: m.text for n, m in scene_nodes(server).items() if n.endswith("/label")}
    assert labels == {f"/hpgs/added/train_{i:04d}/label": f"r{h.round}" for h in dm.history for i in h.chosen_indices}

    shot, bare = tmp_path / "viewer.png", tmp_path / "viewer-without-roles.png"
    url = f"http://127.0.0.1:{viewer.config.websocket_port}/"
    args = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
            "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=args)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            # viser drops the canvas to 0.2x devicePixelRatio while frames are slow (software GL): keep >= 0.5.
            page.add_init_script("Object.defineProperty(window, 'devicePixelRatio', {get: () => 2.5})")
            page.goto(url)
            page.get_by_text("View selection").first.wait_for(timeout=20_000)
            look_at_all_cameras(viewer, pipeline)
            # The panel lists both rounds with their chosen views.
            page.get_by_text("Round 2").first.scroll_into_view_if_needed()
            text = page.inner_text("body")
            for h in dm.history:
                assert f"Round {h.round}" in text and f"step {h.step}" in text
                assert all(name in text for name in h.chosen)
            # Choosing a round in the dropdown highlights its views.
            page.get_by_label("Highlight").click()
            page.get_by_role("option", name="round 1 (step 10)").click()
            page.get_by_text("highest scores").first.wait_for(timeout=5_000)
            highlighted = set(frustum_colours(server, "/hpgs/highlight/"))
            assert highlighted == {f"/hpgs/highlight/train_{i:04d}" for i in dm.history[0].chosen_indices}
            page.get_by_text("View selection").first.scroll_into_view_if_needed()
            time.sleep(1.5)  # the frustums and the splat render
            page.screenshot(path=str(shot))
            # The same view with the roles switched off: the difference is the plugin's frustums.
            page.get_by_label("Show camera roles").uncheck()
            time.sleep(1.0)
            page.screenshot(path=str(bare))
            browser.close()
    finally:
        server.stop()
    with_roles, without = (np.asarray(Image.open(p).convert("RGB")).astype(int) for p in (shot, bare))
    assert with_roles.shape[:2] == (HEIGHT, WIDTH)
    canvas = np.s_[60:, : WIDTH - 340]  # left of the control panel (320 px), below the title bar
    changed = np.abs(with_roles[canvas] - without[canvas]).max(-1) > 40
    drawn = with_roles[canvas][changed]  # [M, 3] pixels of the role frustums
    for role in ("initial", "added", "test", "highlight"):
        near = np.abs(hue(drawn) - hue(np.array([ROLE_COLOURS[role]]))[0])
        near = np.minimum(near, 360 - near) < 8
        assert (near & (np.ptp(drawn, axis=1) > 40)).sum() > 30, f"no {role} frustum on screen ({shot})"


def hue(rgb: np.ndarray) -> np.ndarray:
    """Hue in degrees of RGB pixels [M, 3] (lines are thin and blended, so hue says more than the exact colour)."""
    r, g, b = (rgb[:, k].astype(float) for k in range(3))
    mx, mn = rgb.max(1).astype(float), rgb.min(1).astype(float)
    d = np.maximum(mx - mn, 1e-6)
    h = np.where(mx == r, (g - b) / d % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4))
    return 60 * h


def test_rounds_redraw_the_view_live(tiny_scene, tmp_path):
    """`ns-train hpgs --vis viewer`: the rounds' listener redraws the roles and the panel during training."""
    from nerfstudio.viewer_legacy.server.viewer_utils import get_free_port

    from hpgs_ns.viewer import ROLE_COLOURS

    cfg = _config(tiny_scene, tmp_path)
    cfg.vis = "viewer"
    cfg.viewer.websocket_host = "127.0.0.1"
    cfg.viewer.websocket_port = get_free_port()
    cfg.viewer.quit_on_train_completion = True
    seen = []
    from hpgs_ns.viewer import SelectionView

    original = SelectionView.on_round

    def spy(self, record):
        original(self, record)
        seen.append((record.round, dict(frustum_colours(self.server)), self.rounds_list.content))

    SelectionView.on_round = spy
    try:
        trainer = run_training(cfg)
    finally:
        SelectionView.on_round = original
    try:
        dm = trainer.pipeline.datamanager
        assert [s[0] for s in seen] == [1, 2]
        # The view is no nn.Module: checkpoints keep their keys.
        assert not [k for k in trainer.pipeline.state_dict() if "selection_view" in k]
        for round_, colours, listed in seen:
            record = dm.history[round_ - 1]
            for i in record.chosen_indices:
                assert colours[f"/hpgs/added/train_{i:04d}"] == rgb_int(ROLE_COLOURS["added"])
                assert f"/hpgs/withheld/train_{i:04d}" not in colours
                assert colours[f"/hpgs/highlight/train_{i:04d}"] == rgb_int(ROLE_COLOURS["highlight"])
            assert f"**Round {round_}** · step {record.step}" in listed and f"Round {round_ + 1}" not in listed
    finally:
        trainer.shutdown()
