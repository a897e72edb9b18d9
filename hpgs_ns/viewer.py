"""The view selection in nerfstudio's viewer: cameras coloured by role, and a panel listing the rounds.

nerfstudio's viewer (`ns-viewer --load-config`, `ns-train --vis viewer`) installs every `ViewerElement` it
finds on the pipeline into its Control tab (folder "Custom Elements") and hands it the viser server; the
pipeline holds one `SelectionView`. viser 0.2.7 cannot recolour a frustum once drawn, and nerfstudio draws its
own `/cameras/camera_NNNNN` frustums (training views only, one grey), so the roles are the plugin's own frustums,
drawn a little larger around nerfstudio's so its image thumbnails stay visible inside them:

    /hpgs/initial/train_NNNN     active from step 0
    /hpgs/added/train_NNNN       added by a round (child `label`: "r<round>")
    /hpgs/withheld/train_NNNN    candidates, never trained on (yet)
    /hpgs/test/test_NNNN         the test split
    /hpgs/highlight/train_NNNN   the views of the round chosen in the panel

Each frustum has a child `centre`, a dot in its colour (readable from afar, where viser's thin edges vanish).

Nothing here is an `nn.Module`, so checkpoints' state dict keys do not change; without a viewer (`--vis
tensorboard`, `ns-eval`) the element is never installed and does nothing. Rounds call `on_round` (a listener
of `SelectionRounds`), which redraws only the cameras whose role changed.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import viser
import viser.transforms as vtf
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerElement

from hpgs_ns.selection.records import RoundRecord

RGB = Tuple[int, int, int]

# Okabe-Ito colours: told apart with the common colour-vision deficiencies, and bright on a dark render.
ROLE_COLOURS: Dict[str, RGB] = {
    "initial": (86, 180, 233),  # sky blue
    "added": (230, 159, 0),  # orange
    "withheld": (140, 140, 140),  # grey
    "test": (204, 121, 167),  # reddish purple
    "highlight": (240, 228, 66),  # yellow
}
ROLE_MEANING: Dict[str, str] = {
    "initial": "trained on from step 0",
    "added": "added by round N (label rN)",
    "withheld": "candidates not chosen (yet)",
    "test": "test split, never trained on",
    "highlight": "the round picked below",
}
# Same ratio as nerfstudio.viewer.viewer.VISER_NERFSTUDIO_SCALE_RATIO: viser shows the scene 10x larger.
VISER_SCALE = 10.0
NO_ROUND = "none"


@dataclass(frozen=True)
class CameraRole:
    """What one camera is in the selection: `split` "train" or "test", `index` into that split's cameras."""

    split: str
    index: int
    name: str
    role: str  # a key of ROLE_COLOURS
    round: Optional[int] = None  # the round that added it (role "added")

    @property
    def node(self) -> str:
        """The camera's viser scene node."""
        return f"/hpgs/{self.role}/{self.split}_{self.index:04d}"


def camera_roles(datamanager) -> List[CameraRole]:
    """The role of every training and test camera, from the datamanager's state (also a loaded checkpoint's)."""
    dm = datamanager
    added = {int(i): h.round for h in dm.history for i in h.chosen_indices}
    initial = set(dm.initial_views)
    roles = []
    for i, name in enumerate(dm.image_names):
        role = "added" if i in added else "initial" if i in initial else "withheld"
        roles.append(CameraRole("train", i, name, role, added.get(i)))
    roles += [CameraRole("test", j, name, "test") for j, name in enumerate(dm.test_view_names)]
    return roles


def round_label(record: RoundRecord) -> str:
    """A round's entry in the panel's dropdown."""
    return record.label


def md(text: str) -> str:
    """A view name as literal text in viser's markdown (MDX reads `{`, `<`, `_`, ... as syntax)."""
    return "".join("\\" + c if c in "\\`*_{}[]<>()#+-!|~&" else c for c in str(text))


def top_scores(record: RoundRecord, k: int = 3) -> List[Tuple[str, float]]:
    """The round's k highest-scored candidates (higher = more wanted)."""
    return sorted(record.scores.items(), key=lambda kv: -kv[1])[:k]


def rounds_markdown(history: Sequence[RoundRecord], k: int = 3) -> str:
    """The rounds as the panel shows them: step, chosen views, top scores, seconds."""
    if not history:
        return "*No selection round has run yet.*"
    lines = []
    for h in history:
        tops = ", ".join(f"{md(name)} {score:.3g}" for name, score in top_scores(h, k)) or "-"
        lines.append(
            f"**Round {h.round}** · step {h.step} · {h.seconds:.2f} s  \n"
            f"\\+ {', '.join(md(n) for n in h.chosen)}  \n"
            f"top: {tops}"
        )
    return "\n\n".join(lines)


def legend_markdown(counts: Dict[str, int]) -> str:
    """Colour -> role, with how many cameras have each role (viser's markdown is MDX: JSX spans are allowed)."""
    rows = []
    for role, (r, g, b) in ROLE_COLOURS.items():
        count = f" ({counts[role]})" if role in counts else ""
        chip = f"<span style={{{{color: '#{r:02x}{g:02x}{b:02x}', fontSize: '1.3em'}}}}>■</span>"
        rows.append(f"{chip} **{role}**{count}: {ROLE_MEANING[role]}")
    return "  \n".join(rows)


def frustum_scale(cameras, least: float = 0.16) -> float:
    """Frustum size in viser units: 6% of the cameras' median distance from their centroid, so a capture reads
    the same at any scene scale; never below `least` (~1.6x nerfstudio's own 0.1 frustums, which ours frame).

    cameras: nerfstudio `Cameras` [N]."""
    centres = cameras.camera_to_worlds[:, :3, 3].detach().cpu().double() * VISER_SCALE  # [N, 3]
    spread = float((centres - centres.mean(0)).norm(dim=1).median())
    return max(least, 0.06 * spread)


class SelectionView(ViewerElement):
    """Draws the selection's camera roles and the rounds panel into nerfstudio's viewer (module docstring)."""

    def __init__(self, datamanager, name: str = "View selection") -> None:
        super().__init__(name)
        self.datamanager = datamanager
        self.scale = 0.16  # set at install (frustum_scale)
        self.server: Optional[viser.ViserServer] = None
        self.drawn: Dict[Tuple[str, int], CameraRole] = {}  # what the scene shows now, by (split, index)
        self.nodes: Dict[str, viser.SceneNodeHandle] = {}  # our scene nodes by name (removing one removes its label)
        self.highlighted: List[str] = []  # highlight nodes now in the scene
        self.shown = NO_ROUND  # the round they belong to
        self._lock = threading.RLock()  # rounds call in from the training thread, the GUI from viser's

    # ---- nerfstudio's ViewerElement protocol ------------------------------------------------------------

    def _create_gui_handle(self, viser_server: viser.ViserServer) -> None:
        gui = viser_server.gui
        self.gui_handle = gui.add_folder(self.name)
        with self.gui_handle:
            self.legend = gui.add_markdown("")
            self.show_roles = gui.add_checkbox("Show camera roles", initial_value=True)
            self.round_choice = gui.add_dropdown("Highlight", options=(NO_ROUND,), initial_value=NO_ROUND)
            self.round_details = gui.add_markdown("")
            self.rounds_list = gui.add_markdown("")
        self.show_roles.on_update(lambda _: setattr(self.root, "visible", self.show_roles.value))
        self.round_choice.on_update(lambda _: self.highlight(self.round_choice.value))

    def install(self, viser_server: viser.ViserServer) -> None:
        self.server = viser_server
        self.scale = frustum_scale(self.datamanager.train_dataset.cameras)
        self.root = viser_server.scene.add_frame("/hpgs", show_axes=False)
        self._create_gui_handle(viser_server)
        self.refresh()

    # ---- updates ----------------------------------------------------------------------------------------

    def on_round(self, record: RoundRecord) -> None:
        """`SelectionRounds` listener: redraw after a round and highlight it. Never stops training."""
        try:
            self.refresh()
            self.highlight(round_label(record))
        except Exception as err:  # the viewer is a view; training goes on without it
            CONSOLE.print(f"[yellow]could not show round {record.round} in the viewer: {err}")

    def refresh(self) -> None:
        """Redraw the cameras whose role changed and rewrite the panel (no-op until the viewer installs us)."""
        if self.server is None:
            return
        with self._lock, self.server.atomic():
            roles = camera_roles(self.datamanager)
            for role in roles:
                key = (role.split, role.index)
                if self.drawn.get(key) != role:
                    if key in self.drawn:
                        self.nodes.pop(self.drawn[key].node).remove()
                    self._draw(role)
                    self.drawn[key] = role
            counts: Dict[str, int] = {}
            for role in roles:
                counts[role.role] = counts.get(role.role, 0) + 1
            history = self.datamanager.history
            self.legend.content = legend_markdown(counts)
            self.rounds_list.content = rounds_markdown(history)
            options = (NO_ROUND,) + tuple(round_label(h) for h in history)
            if options != tuple(self.round_choice.options):
                self.round_choice.options = options

    def highlight(self, choice: str) -> None:
        """Mark the views one round added (`choice`: a dropdown entry, or "none") and show that round's details."""
        if self.server is None:
            return
        with self._lock, self.server.atomic():
            record = next((h for h in self.datamanager.history if round_label(h) == choice), None)
            choice = choice if record else NO_ROUND
            if choice == self.shown:  # also ends the dropdown callback that setting its value below fires
                return
            self.shown = choice
            for node in self.highlighted:
                self.nodes.pop(node).remove()
            self.highlighted = []
            if self.round_choice.value != choice:
                self.round_choice.value = choice
            if record is None:
                self.round_details.content = ""
                return
            cameras = self.datamanager.train_dataset.cameras
            for i in record.chosen_indices:
                node = f"/hpgs/highlight/train_{int(i):04d}"
                self._frustum(node, cameras, int(i), ROLE_COLOURS["highlight"], 1.5 * self.scale)
                self.highlighted.append(node)
            tops = "  \n".join(f"{md(name)}: {score:.4g}" for name, score in top_scores(record, 5))
            self.round_details.content = (
                f"**{round_label(record)}**: {record.seconds:.2f} s, {record.num_active} active after it  \n"
                f"chosen: {', '.join(md(n) for n in record.chosen)}  \nhighest scores:  \n{tops or '-'}"
            )

    # ---- drawing ----------------------------------------------------------------------------------------

    def _draw(self, role: CameraRole) -> None:
        dm = self.datamanager
        cameras = (dm.train_dataset if role.split == "train" else dm.eval_dataset).cameras
        handle = self._frustum(role.node, cameras, role.index, ROLE_COLOURS[role.role], self.scale)
        if role.round is not None:
            self.server.scene.add_label(f"{role.node}/label", f"r{role.round}")

        @handle.on_click
        def _(event: viser.SceneNodePointerEvent) -> None:
            # As nerfstudio's own frustums do (ours are larger and catch the click): look through the camera.
            with event.client.atomic():
                event.client.camera.position = event.target.position
                event.client.camera.wxyz = event.target.wxyz

    def _frustum(self, node: str, cameras, index: int, colour: RGB, scale: float) -> viser.CameraFrustumHandle:
        """Camera `index` of a nerfstudio `Cameras` (OpenGL axes, dataparser coordinates) as a viser frustum."""
        c2w = cameras.camera_to_worlds[index].detach().cpu().numpy()  # [3, 4]
        rotation = vtf.SO3.from_matrix(c2w[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)  # OpenGL -> OpenCV axes
        height, width, fy = float(cameras.height[index]), float(cameras.width[index]), float(cameras.fy[index])
        handle = self.server.scene.add_camera_frustum(
            node,
            fov=2 * math.atan(height / (2 * fy)),  # vertical
            aspect=width / height,
            scale=scale,
            color=colour,
            wxyz=rotation.wxyz,
            position=c2w[:3, 3] * VISER_SCALE,
        )
        # viser draws frustum edges as cylinders 3% of the frustum's size thick, under a pixel from afar; a solid
        # dot at the camera centre keeps the role readable there.
        self.server.scene.add_icosphere(f"{node}/centre", radius=0.15 * scale, color=colour, subdivisions=1)
        self.nodes[node] = handle
        return handle
