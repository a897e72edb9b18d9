"""Runs saved by earlier hpgs-ns versions, read by this one: every compatibility rule in one place.

0.1 saved a VanillaPipelineConfig with the selection loop's options on the datamanager; 0.2 the hpgs pipeline with
those options still on the datamanager (`--pipeline.datamanager.selector`, ...). 0.3 moved them to
`--pipeline.selection.*`; 0.4 dropped the old command-line spelling and keeps reading the old config.yml files here,
so `ns-eval`, `ns-viewer` and `--load-config` open old runs. (config.yml files of 0.1 also name two scheduler
classes in `hpgs_ns.trainer`, which YAML looks up there: the trainer re-exports them.) 0.5 moved the restarts from
`--pipeline.selection.after-add.*` and `reset-after-add` to the model's `--pipeline.model.restarts.*`
(`move_restarts`); their resume keys kept their names.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Dict, List, Optional, Tuple

import yaml

# Options that moved from the datamanager to `--pipeline.selection` in 0.3: old name -> new name.
MOVED_FROM_DATAMANAGER: Dict[str, str] = {
    **{name: name for name in ("selector", "select_every", "select_at", "views_per_round", "max_rounds",
                               "eval_each_round", "stop_when_gain_below", "gain_model", "log_candidate_scores",
                               "snapshot_every", "reset_after_add")},
    "selection_short_side": "render_short_side",
}
# The option groups of the selectors 0.2 had (each on the datamanager then).
MOVED_GROUPS: Tuple[str, ...] = ("random", "farthest", "fisher", "hpgs", "condorcet", "blend")


def take_datamanager_options(datamanager: Any, selection: Any) -> Dict[str, str]:
    """Move the selection options an old config.yml set on its datamanager into `selection`, and drop them from the
    datamanager. Returns {old name: new name} of what moved."""
    moved: Dict[str, str] = {}
    state = getattr(datamanager, "__dict__", {})
    for old, new in MOVED_FROM_DATAMANAGER.items():
        value = state.pop(old, None)
        if value is not None:
            setattr(selection, new, value)
            moved[old] = new
    for group in MOVED_GROUPS:
        value = state.pop(group, None)
        # 0.2 saved every group; only one changed from its defaults carries options.
        if value is not None and value != type(value)():
            setattr(selection, group, value)
            moved[group] = group
    return moved


def _new_selection(pipeline_config: type) -> Any:
    """A fresh selection config of the pipeline config class `pipeline_config` (its `selection` field's default): this
    module imports none of the classes whose old files it reads, so any of them can import it."""
    return {f.name: f for f in fields(pipeline_config)}["selection"].default_factory()


# 0.4's restart options (`--pipeline.selection.after-add.*`, a class of their own) -> the fields of the model's
# `restarts` group; the class is gone, so its config.yml tag reads as a plain mapping.
OLD_AFTER_ADD_TAG = "tag:yaml.org,2002:python/object:hpgs_ns.selection.after_add.AfterAddConfig"
RESTART_FIELDS: Dict[str, str] = {"restart_at_views": "at_views", "restart_random_starts": "random_starts",
                                  "restart_active_starts": "active_starts", "restart_seeded_starts": "seeded_starts"}


def _old_after_add(loader: yaml.Loader, node: yaml.Node) -> Dict[str, Any]:
    return dict(loader.construct_mapping(node, deep=True))


for _loader in (yaml.Loader, yaml.UnsafeLoader):
    yaml.add_constructor(OLD_AFTER_ADD_TAG, _old_after_add, Loader=_loader)


def move_restarts(selection: Any, model: Any) -> None:
    """A config.yml of 0.4 or before: its selection's `after_add` and `reset_after_add` into the model's
    `restarts` group (fields 0.5 removed are dropped; the model config has read the group's defaults already)."""
    state = getattr(selection, "__dict__", {})
    after_add, every_round = state.pop("after_add", None), state.pop("reset_after_add", None)
    restarts = getattr(model, "restarts", None)
    if restarts is None:
        return
    old = after_add if isinstance(after_add, dict) else {}  # its tag reads as a mapping (`_old_after_add`)
    for name, new in RESTART_FIELDS.items():
        if name in old:
            value = old[name]
            setattr(restarts, new, tuple(int(n) for n in value) if name == "restart_at_views" else bool(value))
    if every_round is not None:
        restarts.every_round = bool(every_round)


def read_pipeline_state(config: Any, state: dict) -> None:
    """`HpgsPipelineConfig.__setstate__`: a 0.2 config.yml has no `selection`; its options are the datamanager's;
    before 0.5 the restarts were the selection's."""
    config.__dict__.update(state)
    if "selection" not in state:
        config.selection = _new_selection(type(config))
    take_datamanager_options(config.datamanager, config.selection)
    move_restarts(config.selection, getattr(config, "model", None))


def upgrade_pipeline_config(config: Any, pipeline_config: type) -> bool:
    """Turn a config.yml of hpgs-ns 0.1 (a VanillaPipelineConfig, rounds inside the datamanager) into
    `pipeline_config` (the hpgs pipeline's), in place, so resuming it (`--load-config`) still runs the rounds. True if
    it changed."""
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    pipeline = config.pipeline
    # the hpgs datamanager's config (0.1 kept the rounds' options there), named by a field only it has
    if type(pipeline) is VanillaPipelineConfig and hasattr(pipeline.datamanager, "num_initial_views"):
        selection = _new_selection(pipeline_config)
        take_datamanager_options(pipeline.datamanager, selection)
        move_restarts(selection, pipeline.model)
        config.pipeline = pipeline_config(datamanager=pipeline.datamanager, model=pipeline.model, selection=selection)
        return True
    return False


# Resume-signature keys added after checkpoints were written, with the value those checkpoints trained with: a
# checkpoint without the key resumes under it as before.
ADDED_SIGNATURE_KEYS: Dict[str, str] = {"fisher.criterion": "trace"}


def fill_added_signature_keys(saved: Dict[str, str], now: Dict[str, str]) -> Dict[str, str]:
    """`saved` with every key added since it was written (and present `now`) set to the value it trained with."""
    added = {k: v for k, v in ADDED_SIGNATURE_KEYS.items() if k in now and k not in saved}
    return {**saved, **added} if added else saved


# Resume-signature keys of the trainer options 0.5 removed (they did not help on the tuning scenes): the flag each
# checkpoint key stands for. A checkpoint trained with one is refused in one line (`removed_options`).
REMOVED_SIGNATURE_KEYS: Dict[str, str] = {
    "late-view-boost": "--pipeline.datamanager.late-view-boost",
    "sh-degree-by-age": "--pipeline.model.sh-degree-by-age",
    "means-lr-by-age": "--pipeline.model.means-lr-by-age",
    "random-points": "--pipeline.datamanager.random-points",
}
# The after-add options 0.5 removed, as the "after-add" signature names them.
REMOVED_AFTER_ADD = ("refine-steps", "reset-opacity", "lr-rewind", "lr-restart", "restart-at-last-add", "restart-from",
                     "error-points")


def removed_options(saved: Dict[str, str]) -> List[str]:
    """The removed options (as flags with their values) a checkpoint's signature says it trained with."""
    out = [f"{flag} {saved[key]}" for key, flag in REMOVED_SIGNATURE_KEYS.items() if key in saved]
    if str(saved.get("near-cull", "")).endswith(" to end"):
        out.append("--pipeline.model.near-cull-to-end True")
    words = [] if saved.get("after-add", "off") == "off" else saved["after-add"].split(", ")
    out += [f"--pipeline.selection.after-add.{w}" for w in words if w.split(" ", 1)[0] in REMOVED_AFTER_ADD]
    return out


SEEDED_RESTARTS = "after-add.restart-seeded-starts"


def seeded_restarts_key(saved: Dict[str, str], now: Dict[str, str]) -> Dict[str, str]:
    """A checkpoint's signature in today's form for restart-seeded-starts: checkpoints written before it had its own
    key (when it was off by default) name it inside "after-add" only when it was on, and never restarted otherwise."""
    words = [] if saved.get("after-add", "off") == "off" else saved["after-add"].split(", ")
    flag = next((w for w in words if w.startswith("restart-seeded-starts ")), None)
    if flag is None:
        return {**saved, SEEDED_RESTARTS: "False"} if SEEDED_RESTARTS in now and SEEDED_RESTARTS not in saved else saved
    rest = ", ".join(w for w in words if w != flag) or "off"
    out = {**saved, "after-add": rest}
    if SEEDED_RESTARTS in now and SEEDED_RESTARTS not in saved:
        out[SEEDED_RESTARTS] = flag.split(" ", 1)[1]
    return out


def restart_flags(key: str, saved: Optional[str]) -> str:
    """The `--pipeline.model.restarts.*` flags that give a checkpoint's restart key back (the keys keep 0.4's
    names: `after-add`, `reset-after-add`, `after-add.restart-{active,seeded}-starts`)."""
    flag = "--pipeline.model.restarts."
    if key == "reset-after-add":
        return f"{flag}every-round {saved or 'False'}"
    if key.startswith("after-add.restart-"):
        return f"{flag}{key[len('after-add.restart-'):]} {saved or 'True'}"
    words = [] if saved in (None, "off") else saved.split(", ")
    if not words:
        return f"without {flag}at-views, with {flag}random-starts and active-starts True"
    return " ".join(flag + w[len("restart-"):] for w in words)


def near_cull_flags(saved: Optional[str]) -> str:
    """The near-cull options that give a checkpoint's "near-cull" signature back (`None`: it had none)."""
    if saved is None:
        return "--pipeline.model.near-cull.screen 0: the active start had no floater guard before 0.4"
    words = saved.split()
    flags = f"--pipeline.model.near-cull.screen {words[0]} --pipeline.model.near-cull.depth {words[1]}"
    flags += f" --pipeline.model.near-cull.support {words[words.index('support') + 1] if 'support' in words else 1}"
    return flags


# The floater guard's options before it was a strategy (0.4): model config field -> the `near-cull` group's field.
NEAR_CULL_FIELDS: Dict[str, str] = {"near_cull_screen": "screen", "near_cull_depth": "depth", "near_cull_support": "support"}


def read_model_state(config: Any) -> None:
    """A model config.yml of 0.4 kept the floater guard's options as `near_cull_*` fields: into the `near_cull`
    group (`ns-eval`, `ns-viewer`, `--load-config` read it as it trained)."""
    state = config.__dict__
    old = {new: state.pop(name) for name, new in NEAR_CULL_FIELDS.items() if name in state}
    if old:
        from hpgs_ns.strategies.near_cull import NearCullConfig

        config.near_cull = NearCullConfig(**old)


def strategy_states(extra_state: Dict[str, Any]) -> Dict[str, Dict[str, Any]]:
    """{strategy name: its saved state} from a model checkpoint's extra state; 0.4 saved the guard's count alone."""
    if "strategies" in extra_state:
        return dict(extra_state["strategies"])
    return {"near-cull": {"culled": int(extra_state.get("near_culled", 0))}}


def read_datamanager_state(config: Any) -> None:
    """A datamanager config.yml of 0.4 or earlier may say `strict_init: true` (removed in 0.5): that run started from
    the points two initial views see, as `seed-points colmap-initial` does now."""
    if config.__dict__.pop("strict_init", False):
        config.seed_points = "colmap-initial"


def view_names_now(saved: Optional[List[str]], names: List[str]) -> Optional[Dict[str, str]]:
    """A datamanager checkpoint's view names (`saved`) against the split's now (`names`): {} when they are the same,
    {saved name: name now} for a checkpoint of 0.1 (bare file names), None when they belong to another scene or split."""
    if saved == names:
        return {}
    from pathlib import Path

    by_file = {Path(n).name: n for n in names}
    if saved == [Path(n).name for n in names]:
        return by_file
    return None
