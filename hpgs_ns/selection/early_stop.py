"""Skip what a scene does not need: stop adding views once the next one is predicted to gain less than X dB.

`GainModel` is the run-time part: per selector, the predicted test-PSNR gain of the view a round adds, as
a + b * log(views), fitted offline, leave one scene out, on runs that record their test PSNR at every round (a
view's gain is measured against a run that trains the same steps on the initial views alone, since training alone
also raises the PSNR). The score of the pick is not used yet.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

# Fitted on FisherRF-protocol runs of six benchmark scenes (docs/early-stop.md): another schedule or resolution
# wants its own.
DEFAULT_GAIN_MODEL = Path(__file__).resolve().parent.parent / "assets" / "gain-model.json"
ALL = "*"  # the average over selectors


@dataclass
class GainModel:
    """Predicted test-PSNR change (dB) over the round that adds a view to `views` views, per selector."""

    coefficients: Dict[str, Tuple[float, float]] = field(default_factory=dict)
    """selector (or "*") -> (a, b): gain = a + b * log(views)."""
    fitted_on: List[str] = field(default_factory=list)
    """The scenes the model was fitted on."""

    def predict(self, selector: str, views: int) -> float:
        a, b = self.coefficients.get(selector, self.coefficients[ALL])
        return a + b * math.log(max(views, 1))

    def save(self, path: Path) -> Path:
        from hpgs_ns.atomic_write import write_json_atomic

        return write_json_atomic(Path(path), {"coefficients": {k: list(v) for k, v in self.coefficients.items()},
                                              "fitted_on": self.fitted_on, "model": "gain = a + b * log(views)"})

    @classmethod
    def load(cls, path: Optional[Path] = None) -> GainModel:
        from hpgs_ns.errors import UserError

        path = Path(path) if path is not None else DEFAULT_GAIN_MODEL
        shipped = "" if path == DEFAULT_GAIN_MODEL else " (or leave it out for the shipped model)"
        if not path.is_file():
            raise UserError(f"no gain model at {path}: pass --pipeline.selection.gain-model FILE{shipped} or drop "
                            "--pipeline.selection.stop-when-gain-below")
        try:
            data = json.loads(path.read_text())
            return cls({k: (float(a), float(b)) for k, (a, b) in data["coefficients"].items()}, list(data.get("fitted_on", [])))
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise UserError(f"gain model {path} is not readable ({err}); pass another --pipeline.selection.gain-model"
                            f"{shipped} or drop --pipeline.selection.stop-when-gain-below") from None
