"""How a benchmark run adds views: the HP-GS and FisherRF protocols, and the rows every selector is compared with.

`hpgs`: 20 initial views evenly spaced along the capture, one more every 2000 steps, 15000 steps (HP-GS).
`fisherrf`: 4 initial views by farthest-point sampling, one more every |train| x 100 steps up to 20 views,
20000 steps (FisherRF, Jiang et al., ECCV 2024). Reference rows: `initial` (no views added) and `all` (every
training view from step 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Tuple

from hpgs_lab.names import REFERENCES
from hpgs_ns.selectors.registry import BUILTIN_SELECTORS, selector_names


def row_order() -> List[str]:
    """Selectors in the registry's order, then the reference rows: how tables and plots list them."""
    return selector_names() + list(REFERENCES)


# The built-in selectors, in the registry's order: `hpgs bench --help` shows them as the default of --selectors (the
# registry imports no torch, so reading its names costs nothing).
DEFAULT_SELECTORS: Tuple[str, ...] = tuple(BUILTIN_SELECTORS)


@dataclass(frozen=True)
class Protocol:
    """How many views to start from and when to add more."""

    name: str
    steps: int
    initial_views: int
    initial_mode: str
    select_every: int = 0
    select_at: Tuple[int, ...] = ()
    max_rounds: int = 7


def fisherrf_schedule(initial: int = 4, final: int = 20, per_view: int = 100) -> Tuple[int, ...]:
    """FisherRF adds a view every |train| x 100 steps: 400, 900, 1500, ... up to `final` views."""
    steps, t = [], 0
    for n in range(initial, final):
        t += n * per_view
        steps.append(t)
    return tuple(steps)


PROTOCOLS = {
    "hpgs": Protocol("hpgs", steps=15000, initial_views=20, initial_mode="even", select_every=2000, max_rounds=7),
    "fisherrf": Protocol(
        "fisherrf", steps=20000, initial_views=4, initial_mode="fps", select_at=fisherrf_schedule(), max_rounds=16
    ),
}


def scaled(protocol: Protocol, scale: float) -> Protocol:
    """The protocol with every step count multiplied by `scale` (short CPU runs keep the same shape)."""
    if scale == 1.0:
        return protocol
    return Protocol(
        protocol.name,
        steps=max(int(protocol.steps * scale), 1),
        initial_views=protocol.initial_views,
        initial_mode=protocol.initial_mode,
        select_every=max(int(protocol.select_every * scale), 1) if protocol.select_every else 0,
        select_at=tuple(max(int(s * scale), 1) for s in protocol.select_at),
        max_rounds=protocol.max_rounds,
    )
