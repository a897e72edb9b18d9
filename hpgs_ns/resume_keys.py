"""Which options a resumed run must keep: marked on the config dataclasses' fields, read into the checkpoint's resume
signature (`HpgsTrainer` refuses a resume that changes one, in one line).

A field marked `metadata=resume(text)` joins the signature as {its flag's name: `text(value)`}; the text is what
checkpoints already hold, so a field's formatter never changes once written (`hpgs_ns.compat` reads older ones).
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Callable, Dict, Optional

KEY = "resume"


def resume(text: Callable[[Any], str] = str, key: Optional[str] = None) -> Dict[str, Any]:
    """Field metadata: this option is kept across a resume, written as `text(value)` under `key` (default: the
    field's name with dashes, as its flag spells it)."""
    return {KEY: (key, text)}


def signature_of(config: Any) -> Dict[str, str]:
    """{key: text} of `config`'s marked fields."""
    out: Dict[str, str] = {}
    for f in fields(config):
        mark = f.metadata.get(KEY)
        if mark is not None:
            key, text = mark
            out[key or f.name.replace("_", "-")] = text(getattr(config, f.name))
    return out
