"""Property-based tests of the lab's readers (#44): a suite TOML and a benchmark result, valid files truncated,
with bytes flipped, or with a field given a value of another type, read as valid files or fail with the reader's
one-line error naming the file: never another exception. The generators and the property: tests/fuzzing.py (the
plugin's readers: tests/plugin/test_fuzz_readers.py).
"""

from __future__ import annotations

import json

import pytest
from conftest import REPO
from fuzzing import damaged, fuzz, json_variants, reads_or_one_line, retyped
from hypothesis import given
from hypothesis import strategies as st

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
