"""`selected_views.json`, the round log of a run: a typed, versioned `SelectionLog`.

The trainer writes it (`rounds.SelectionRounds.write_log`: at the first step, once per finished round, at the end);
`hpgs demo`, `hpgs bench` and the benchmarks read it with `SelectionLog.read`. Version 1 had no `version` key and
the same fields; version 2 adds the key. A file that cannot be read is one `RoundLogError` naming it and the fix.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from hpgs_ns.atomic_write import write_json_atomic
from hpgs_ns.errors import UserError
from hpgs_ns.selection.records import RoundRecord, StopRecord

FILE_NAME = "selected_views.json"
VERSION = 2


class RoundLogError(UserError, ValueError):
    """A `selected_views.json` that cannot be read."""


@dataclass
class SelectionLog:
    """Which views a run trained on and how it came to them."""

    selector: str
    seed: int
    initial: List[str]
    """Views active from the start (names)."""
    rounds: List[RoundRecord] = field(default_factory=list)
    active: List[str] = field(default_factory=list)
    """Views active now (after the last round)."""
    withheld: List[str] = field(default_factory=list)
    """Training views never added."""
    test: List[str] = field(default_factory=list)
    reset_after_add: bool = False
    """Whether the splat restarted after every round (`--pipeline.model.restarts.every-round`; the log's key keeps
    its first name)."""
    seed_points: Optional[str] = None
    """The start mode as resolved (`auto` reads as colmap or active)."""
    random_start: bool = False
    """Whether that mode found no points and the splat started from random ones."""
    peak_gpu_memory_mb: Optional[float] = None
    stopped: Optional[StopRecord] = None
    """Why stop-when-gain-below ended selection, if it did."""
    test_psnr_at_round_steps: Dict[int, float] = field(default_factory=dict)
    """eval-each-round: test PSNR at every scheduled step, before its round if one ran."""
    version: int = VERSION

    @property
    def chosen(self) -> List[str]:
        """Every view the rounds added, in the order they were added."""
        return [v for r in self.rounds for v in r.chosen]

    def to_dict(self) -> Dict[str, Any]:
        return {
            "version": VERSION, "selector": self.selector, "seed": int(self.seed),
            "reset_after_add": bool(self.reset_after_add), "seed_points": self.seed_points,
            "random_start": bool(self.random_start), "initial": list(self.initial),
            "rounds": [r.to_dict() for r in self.rounds], "active": list(self.active),
            "withheld": list(self.withheld), "test": list(self.test), "peak_gpu_memory_mb": self.peak_gpu_memory_mb,
            "stopped": self.stopped.to_dict() if self.stopped is not None else None,
            "test_psnr_at_round_steps": {str(k): float(v) for k, v in sorted(self.test_psnr_at_round_steps.items())},
        }

    @classmethod
    def from_dict(cls, data: Dict[str, Any]) -> SelectionLog:
        if not isinstance(data, dict) or not isinstance(data.get("rounds"), list):
            raise TypeError("no list of rounds")
        version = int(data.get("version", 1))
        if version > VERSION:
            raise ValueError(f"version {version} is newer than this hpgs_ns reads ({VERSION}); upgrade hpgs_ns")
        for key in ("initial", "active", "withheld", "test"):
            if not isinstance(data.get(key, []), list) or not all(isinstance(n, str) for n in data.get(key, [])):
                raise TypeError(f"{key} is not a list of view names")
        rounds = [RoundRecord.from_dict(entry) for entry in data["rounds"]]
        for record in rounds:
            if not all(isinstance(n, str) for n in record.chosen):
                raise TypeError(f"round {record.round} chose {record.chosen!r}")
        memory = data.get("peak_gpu_memory_mb")
        return cls(
            selector=str(data.get("selector", "")), seed=int(data.get("seed", 0)), initial=list(data.get("initial", [])),
            rounds=rounds, active=list(data.get("active", [])), withheld=list(data.get("withheld", [])),
            test=list(data.get("test", [])), reset_after_add=bool(data.get("reset_after_add", False)),
            seed_points=data.get("seed_points"), random_start=bool(data.get("random_start", False)),
            peak_gpu_memory_mb=float(memory) if memory is not None else None,
            stopped=StopRecord.from_dict(data["stopped"]) if data.get("stopped") else None,
            test_psnr_at_round_steps={int(k): float(v) for k, v in (data.get("test_psnr_at_round_steps") or {}).items()},
        )

    def write(self, path: Path) -> Path:
        """Temp file, then rename: a reader never sees half a log."""
        return write_json_atomic(Path(path), self.to_dict())

    @classmethod
    def read(cls, path: Path) -> SelectionLog:
        """A run's `selected_views.json` (a run folder is read as its log), or RoundLogError naming it and the fix."""
        path = Path(path)
        if path.is_dir():
            path = path / FILE_NAME
        fix = "re-run the training (a finished run writes it), or restore it from a copy"
        if not path.is_file():
            raise RoundLogError(f"{path} not found; {fix}")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:  # UnicodeDecodeError and json's errors are ValueErrors
            raise RoundLogError(f"{path} is not readable JSON ({type(err).__name__}: {str(err)[:120]}); {fix}") from None
        try:
            return cls.from_dict(data)
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise RoundLogError(f"{path} is not a round log ({type(err).__name__}: {str(err)[:120]}); {fix}") from None
