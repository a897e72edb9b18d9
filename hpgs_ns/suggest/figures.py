"""What `hpgs suggest` shows a person: the current renders from the suggested poses, and a map of the capture."""

from __future__ import annotations

from pathlib import Path
from typing import List, Sequence

import numpy as np
import torch

from hpgs_ns.atomic_write import atomic_path


def contact_sheet(renders: Sequence[torch.Tensor], scores: Sequence[float], selector: str, path: Path) -> Path:
    """The splat rendered from each suggested pose (what it looks like there now), ranked, with its score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(renders)
    cols = min(n, 5)
    rows = -(-n // cols)
    h, w = renders[0].shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(2.8 * cols, 2.8 * rows * h / w + 0.5), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for k, (image, score) in enumerate(zip(renders, scores)):
        ax = axes.flat[k]
        ax.imshow(image.detach().cpu().clamp(0, 1).numpy())
        ax.set_title(f"{k + 1}. {selector} {score:.3g}", fontsize=9)
    fig.suptitle("suggested next photos: the splat rendered from there now", fontsize=10)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def top_down_map(dm, poses: torch.Tensor, pool: List[int], picked: List[int], lay, path: Path) -> Path:
    """Top-down (along the capture's up axis): photos trained on, withheld and test views, the candidates scored,
    and the suggestions numbered with their viewing direction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    u = lay.up.double()
    side = torch.tensor([1.0, 0, 0], dtype=u.dtype) if abs(u[0]) < 0.9 else torch.tensor([0, 1.0, 0], dtype=u.dtype)
    a = torch.nn.functional.normalize(torch.linalg.cross(u, side, dim=0), dim=0)
    b = torch.linalg.cross(u, a, dim=0)

    def xy(c2w: torch.Tensor) -> np.ndarray:
        rel = c2w[:, :3, 3].double() - lay.centre.double()
        return torch.stack([rel @ a, rel @ b], -1).numpy()

    train = dm.train_dataset.cameras.camera_to_worlds
    active = set(getattr(dm, "active", range(len(train))))
    fig, ax = plt.subplots(figsize=(5.6, 5.6))
    p = xy(poses[torch.tensor(pool, dtype=torch.long)])
    ax.scatter(p[:, 0], p[:, 1], s=8, c="#cccccc", marker="x", label="candidates scored")
    withheld = [i for i in range(len(train)) if i not in active]
    if withheld:
        q = xy(train[torch.tensor(withheld)])
        ax.scatter(q[:, 0], q[:, 1], s=10, c="#999999", label="photos withheld")
    q = xy(train[torch.tensor(sorted(active))])
    ax.scatter(q[:, 0], q[:, 1], s=14, c="C0", label="photos trained on")
    t = xy(dm.eval_dataset.cameras.camera_to_worlds)
    ax.scatter(t[:, 0], t[:, 1], s=14, c="C4", marker="s", label="test photos")
    s = xy(poses[torch.tensor(picked, dtype=torch.long)])
    forward = -poses[torch.tensor(picked, dtype=torch.long), :3, 2].double()
    d = torch.stack([forward @ a, forward @ b], -1).numpy()
    scale = 0.08 * float(np.ptp(np.concatenate([q, p]), axis=0).max() or 1.0)
    ax.scatter(s[:, 0], s[:, 1], s=60, c="C3", label="suggested (numbered)", zorder=4)
    for k, ((x, y), (dx, dy)) in enumerate(zip(s, d), 1):
        ax.annotate("", (x + scale * dx, y + scale * dy), (x, y), arrowprops=dict(arrowstyle="->", color="C3"))
        ax.annotate(str(k), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=10, weight="bold")
    ax.scatter([0], [0], c="k", marker="+", s=60, label="scene centre")
    ax.set(aspect="equal", xticks=[], yticks=[], title="where to take the next photos (top-down)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=3, frameon=False)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path
