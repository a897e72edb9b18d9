"""What the selection loop records: one `RoundRecord` per round, and a `StopRecord` when early stop ends it.

The datamanager keeps the records (they go into every checkpoint as plain dicts, `to_dict`), the round log
`selected_views.json` (`log.SelectionLog`) lists them, and the viewer and the candidate log read them. `from_dict` reads the dicts of
every earlier version (0.1 logs lack `work`, older ones `reset`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Tuple

if TYPE_CHECKING:  # the lab reads records without torch, which the strategies import
    from hpgs_ns.strategies.base import PointsOutcome


@dataclass
class RoundRecord:
    """One selection round: when it ran, what it added, and what it cost."""

    round: int
    """1 for the first round."""
    step: int
    """Training step the round ran before."""
    selector: str
    chosen: List[str]
    """Names of the views the round added, in the order they were picked."""
    chosen_indices: List[int]
    """The same views as indices into the training split."""
    seconds: float
    """Wall time of the selector's `select` call."""
    num_active: int
    """Active views after the round."""
    test_psnr_before: Optional[float] = None
    """eval-each-round: test PSNR just before the round."""
    reset: bool = False
    """Whether a restart (`--pipeline.model.restarts.*`) put the splat back to its step-0 state after this round."""
    scores: Dict[str, float] = field(default_factory=dict)
    """Score of every candidate the selector looked at (higher = more wanted), by view name."""
    work: Dict[str, float] = field(default_factory=dict)
    """What the selector computed and skipped (`Selection.work`)."""
    num_gaussians_before_reset: Optional[int] = None
    num_gaussians_after_reset: Optional[int] = None
    after_add: Dict[str, float] = field(default_factory=dict)
    """`seed-points active`'s points after this round, as the round log writes them (`PointsOutcome.fields`)."""

    def to_dict(self) -> Dict[str, Any]:
        """Plain types only (checkpoints load with `torch.load(weights_only=True)`); the reset counts only when a
        reset ran, as the round log has always written them."""
        out: Dict[str, Any] = {
            "round": int(self.round), "step": int(self.step), "selector": self.selector, "chosen": list(self.chosen),
            "chosen_indices": [int(i) for i in self.chosen_indices], "seconds": float(self.seconds),
            "num_active": int(self.num_active), "test_psnr_before": self.test_psnr_before, "reset": bool(self.reset),
            "scores": {k: float(v) for k, v in self.scores.items()}, "work": {k: float(v) for k, v in self.work.items()},
        }
        if self.num_gaussians_before_reset is not None:
            out["num_gaussians_before_reset"] = int(self.num_gaussians_before_reset)
            out["num_gaussians_after_reset"] = int(self.num_gaussians_after_reset or 0)
        if self.after_add:
            out["after_add"] = {k: float(v) for k, v in self.after_add.items()}
        return out

    @classmethod
    def from_dict(cls, data: Dict[str, Any]) -> RoundRecord:
        return cls(
            round=int(data["round"]), step=int(data["step"]), selector=str(data.get("selector", "")),
            chosen=list(data["chosen"]), chosen_indices=[int(i) for i in data.get("chosen_indices", [])],
            seconds=float(data.get("seconds", 0.0)), num_active=int(data.get("num_active", 0)),
            test_psnr_before=data.get("test_psnr_before"), reset=bool(data.get("reset", False)),
            scores={k: float(v) for k, v in data.get("scores", {}).items()},
            work={k: float(v) for k, v in data.get("work", {}).items()},
            num_gaussians_before_reset=data.get("num_gaussians_before_reset"),
            num_gaussians_after_reset=data.get("num_gaussians_after_reset"),
            after_add={k: float(v) for k, v in data.get("after_add", {}).items()},
        )

    @property
    def label(self) -> str:
        """The round as the viewer's dropdown names it."""
        return f"round {self.round} (step {self.step})"


@dataclass(frozen=True)
class RoundFollowUp:
    """What followed a round's add: each trainer strategy's outcome (a restart, `hpgs_ns.strategies`), then
    `seed-points active`'s points (None: none added)."""

    outcomes: Tuple[Any, ...] = ()
    """Frozen dataclasses with `recorded_in(record)`, in the strategies' order."""
    points: Optional[PointsOutcome] = None

    def recorded_in(self, record: RoundRecord) -> RoundRecord:
        """`record` with what followed its add."""
        for outcome in self.outcomes:
            record = outcome.recorded_in(record)
        if self.points is not None:
            record = self.points.recorded_in(record)
        return record


@dataclass
class StopRecord:
    """Why stop-when-gain-below ended selection early."""

    step: int
    views: int
    """Active views when selection stopped."""
    predicted_gain_db: float
    threshold_db: float

    def to_dict(self) -> Dict[str, Any]:
        return {"step": int(self.step), "views": int(self.views), "predicted_gain_db": float(self.predicted_gain_db),
                "threshold_db": float(self.threshold_db)}

    @classmethod
    def from_dict(cls, data: Dict[str, Any]) -> StopRecord:
        return cls(int(data["step"]), int(data["views"]), float(data["predicted_gain_db"]), float(data["threshold_db"]))
