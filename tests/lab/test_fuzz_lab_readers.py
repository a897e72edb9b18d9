"""Property-based tests of the lab's readers (#44): a suite TOML and a benchmark result, valid files truncated,
with bytes flipped, or with a field given a value of another type, read as valid files or fail with the reader's
one-line error naming the file: never another exception. The plugin's readers, with the same generators:
tests/plugin/test_fuzz_readers.py.

Examples are bounded and derandomized (the same examples every run, `derandomize=True`), so CI neither flakes nor
takes long; `HPGS_FUZZ_EXAMPLES` scales every test's count for a longer local run.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, List

import pytest
from conftest import REPO
from hypothesis import HealthCheck, given, settings
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


# ---- suite TOML -----------------------------------------------------------------------------------------------

SUITE = """description = "fuzz"

[[scene]]
name = "ring"
path = "synthetic:ring"
dataparser = "mipnerf360"
options = { downscale-factor = 2, eval-mode = "interval" }
smoke = false

[[scene]]
name = "grid"
path = "synthetic:grid"
"""


def test_suites_of_another_shape_or_damaged_read_or_fail_in_one_line(tmp_path):
    from hpgs_lab.suites import SuiteError, load_suite, tomllib

    path = tmp_path / "suite.toml"
    spec = tomllib.loads(SUITE)

    def as_toml(tree) -> bytes:
        # a minimal TOML writer for the shapes `retyped` makes (JSON values are valid TOML inline values, bar null)
        def value(v):
            if v is None or (isinstance(v, float) and v != v):
                return '"none"'
            if isinstance(v, bool):
                return "true" if v else "false"
            if isinstance(v, dict):
                return "{ " + ", ".join(f"{json.dumps(str(k))} = {value(x)}" for k, x in v.items()) + " }"
            if isinstance(v, list):
                return "[" + ", ".join(value(x) for x in v) + "]"
            if isinstance(v, float) and v in (float("inf"), float("-inf")):
                return "inf" if v > 0 else "-inf"
            return json.dumps(v)

        return "\n".join(f"{json.dumps(str(k))} = {value(v)}" for k, v in tree.items()).encode()

    @fuzz(60)
    @given(st.one_of(retyped(spec).map(as_toml), damaged(SUITE.encode())))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: load_suite(str(path)), path, SuiteError)

    check()


# ---- bench results --------------------------------------------------------------------------------------------


def test_damaged_bench_results_read_or_fail_in_one_line(tmp_path):
    from hpgs_lab.results import ResultError, RunResult

    source = REPO / "benchmarks" / "results" / "suite" / "juicebox" / "hpgs" / "farthest" / "seed3.json"
    if not source.is_file():
        pytest.skip(f"{source} not found")
    result = RunResult.from_json(source).to_dict()
    result["test_views"] = result["test_views"][:2]
    path = tmp_path / "seed3.json"

    @fuzz(60)
    @given(json_variants(result))
    def check(data):
        path.write_bytes(data)
        reads_or_one_line(lambda: RunResult.from_json(path), path, ResultError)

    check()
