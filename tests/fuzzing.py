"""The damaged and retyped files the readers' property tests feed them (tests/plugin/test_fuzz_readers.py, the
plugin's readers; tests/lab/test_fuzz_lab_readers.py, the lab's), and the property they check: a reader returns, or
fails with its one-line error naming the file.

Examples are bounded and derandomized (the same examples every run), so CI neither flakes nor takes long;
`HPGS_FUZZ_EXAMPLES` scales every test's count for a longer local run.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, List

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from hpgs_ns.errors import UserError

SCALE = float(os.environ.get("HPGS_FUZZ_EXAMPLES", "1"))


def fuzz(examples: int):
    return settings(max_examples=max(1, int(examples * SCALE)), derandomize=True, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def damaged(data: bytes):
    """A truncation, or one to four flipped bytes, of `data`."""
    cut = st.integers(0, max(len(data) - 1, 0)).map(lambda n: data[:n])
    flips = st.lists(st.tuples(st.integers(0, len(data) - 1), st.integers(1, 255)), min_size=1, max_size=4)

    def flip(changes) -> bytes:
        out = bytearray(data)
        for at, mask in changes:
            out[at] ^= mask
        return bytes(out)

    return st.one_of(cut, flips.map(flip))


OTHER_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-3, 10**12), st.floats(allow_nan=True), st.text(max_size=4),
                         st.lists(st.integers(0, 3), max_size=3), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


def paths_in(tree: Any, prefix=()) -> List[tuple]:
    """Every key path of a nested dict/list."""
    found = []
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for key, value in items:
        found.append(prefix + (key,))
        found += paths_in(value, prefix + (key,))
    return found


def retyped(tree: Any):
    """`tree` (JSON-like) with one field, at any depth, given a value of another type."""
    paths = paths_in(tree)

    def change(choice) -> Any:
        path, value = choice
        out = json.loads(json.dumps(tree))
        node = out
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
        return out

    return st.tuples(st.sampled_from(paths), OTHER_VALUES).map(change)


def json_variants(tree: Any):
    """The bytes of `tree` as a JSON file with one field retyped (`retyped`), or its bytes damaged (`damaged`)."""
    return st.one_of(retyped(tree).map(lambda t: json.dumps(t).encode()), damaged(json.dumps(tree).encode()))


def reads_or_one_line(read: Callable[[], Any], path: Path, errors=(UserError,)) -> None:
    """`read()` returns, or raises one of `errors` whose message is one line naming `path` (or its folder)."""
    try:
        read()
    except errors as err:
        message = str(err)
        assert "\n" not in message and message, message
        assert str(path) in message or str(path.parent) in message, message
