"""An analysis log of every round: every selector's score of every candidate, beside an oracle.

With `--pipeline.selection.log-candidate-scores True`, after each round (its choice already made, so nothing here
can change it) every registered selector whose config says `logged_in_candidate_log` (all but `random` and `blend`)
scores the candidates the round saw, and each candidate's
current render is measured against its withheld photo (PSNR, SSIM, LPIPS): the error a selector tries to guess
without the photo. `candidate_scores.jsonl` in the run folder gets one line per round. It is for tuning selectors
offline, leave one scene out (`blend`'s weights were fitted on such logs); a run never reads it back. The random stream is
forked while logging, so a run's own numbers do not depend on whether it logs.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Dict, List

import torch

from hpgs_ns.selection.records import RoundRecord
from hpgs_ns.selectors import registry


def logged_selectors() -> List[str]:
    """Every registered selector the log scores candidates with (`logged_in_candidate_log`), in the registry's order."""
    return [name for name in registry.selector_names() if registry.selector_class(name).logged_in_candidate_log]


class CandidateLog:
    """A round listener of `SelectionRounds` (see the module docstring)."""

    def __init__(self, rounds) -> None:
        self.rounds = rounds
        self.selectors: Dict[str, Any] = {}

    def selector(self, name: str):
        """The run's own options of each selector, set up once."""
        if name not in self.selectors:
            self.selectors[name] = self.rounds.config.selector_config(name).setup()
        return self.selectors[name]

    def on_round(self, record: RoundRecord) -> None:
        if self.rounds.run_dir is None:
            return
        with torch.random.fork_rng(devices=[torch.device(self.rounds.model.device)] if torch.cuda.is_available() else []):
            line = self.measure(record)
        path = Path(self.rounds.run_dir) / "candidate_scores.jsonl"
        with open(path, "a", encoding="utf-8") as f:  # appended whole lines: a killed run loses at most one round
            f.write(json.dumps(line) + "\n")

    @torch.no_grad()
    def measure(self, record: RoundRecord) -> Dict[str, Any]:
        from hpgs_ns.metrics import lpips, photo_rgb, psnr, ssim

        dm, model = self.rounds.datamanager, self.rounds.model
        chosen = list(record.chosen_indices)
        # The round as the selector saw it: before its picks joined the active set.
        context = self.rounds.context(record.step)
        context.active = [i for i in context.active if i not in chosen]
        context.candidates = sorted(context.candidates + chosen)
        context.num_to_pick = 1
        names = dm.image_names
        line: Dict[str, Any] = {
            "step": record.step, "round": record.round, "selector": record.selector,
            "chosen": [names[i] for i in chosen], "active": [names[i] for i in context.active],
            "candidates": [names[i] for i in context.candidates], "scores": {}, "seconds": {},
        }
        for name in logged_selectors():
            start = time.perf_counter()
            scores = self.selector(name).select(context).scores
            line["scores"][name] = [float(scores.get(c, float("nan"))) for c in context.candidates]
            line["seconds"][name] = time.perf_counter() - start
        start = time.perf_counter()
        cameras = dm.train_dataset.cameras[torch.tensor(context.candidates, dtype=torch.long)]
        renders = model.render_views(cameras)
        oracle: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": []}
        for index, render in zip(context.candidates, renders):
            photo = photo_rgb(dm.cached_train[index]["image"]).to(render.device)
            oracle["psnr"].append(psnr(render, photo))
            oracle["ssim"].append(ssim(render, photo))
            oracle["lpips"].append(lpips(render, photo))
        line["oracle"] = oracle
        line["seconds"]["oracle"] = time.perf_counter() - start
        return line
