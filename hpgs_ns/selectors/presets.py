"""Named combinations of the built-in selectors, each one line of the registry (`hpgs_ns.selectors.registry`), so a
run (and `hpgs bench`) names each like a selector.

- `fisher-dopt`: `fisher` with the D-optimal criterion (POp-GS, CVPR'25): `sum log(1 + h_c / (H_train + lambda))`.
- `farthest-dopt`: `farthest`'s best 20% of the candidates, reranked by D-optimal `fisher` (a geometric shortlist
  reranked by information, as AGILE-GS+ does).

Each is its parts' options under one group (`--pipeline.selection.farthest-dopt.then.probes 8`,
`--pipeline.selection.farthest-dopt.shortlist-size 0.3`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Tuple

from hpgs_ns.selectors.farthest import FarthestSelectorConfig
from hpgs_ns.selectors.fisher import FisherSelectorConfig
from hpgs_ns.selectors.shortlist import ShortlistPresetConfig


@dataclass
class FisherDoptSelectorConfig(FisherSelectorConfig):
    """`fisher` with the D-optimal criterion (POp-GS): the log-det gain of each candidate's diagonal information."""

    criterion: str = "dopt"
    logged_in_candidate_log: ClassVar[bool] = False  # `fisher`'s own row holds the same renders' trace scores


def dopt_fisher() -> FisherSelectorConfig:
    return FisherSelectorConfig(criterion="dopt")


@dataclass
class FarthestDoptSelectorConfig(ShortlistPresetConfig):
    """`farthest`'s best `shortlist-size` share of the candidates (its greedy far-apart order), reranked by
    D-optimal `fisher`."""

    code_files: ClassVar[Tuple[str, ...]] = ("selectors/farthest.py", "selectors/fisher.py", "selectors/shortlist.py",
                                             "render/pair_render.py")
    first: FarthestSelectorConfig = field(default_factory=FarthestSelectorConfig)
    """The shortlisting selector's options."""
    then: FisherSelectorConfig = field(default_factory=dopt_fisher)
    """The ranking selector's options."""
