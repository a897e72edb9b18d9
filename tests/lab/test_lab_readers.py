"""What the lab reads, damaged: a suite TOML (through `hpgs bench`) and a benchmark result are one-line errors
naming the file. (The plugin's readers: tests/plugin/test_readers.py.)"""

from __future__ import annotations

import json

import pytest
from conftest import REPO
from helpers import hpgs_error, one_line

from hpgs_lab.results import ResultError, RunResult
from hpgs_lab.suites import SuiteError, load_suite


@pytest.fixture(autouse=True)
def lab_registered(monkeypatch):
    """`hpgs bench` found as an installed lab registers it (tests/lab/test_lab_cli.py checks the registration)."""
    from hpgs_lab.cli import bench

    monkeypatch.setattr("hpgs_ns.cli.registered_commands", lambda: {"bench": bench})


# ---- suite TOML (hpgs bench) ----------------------------------------------------------------------------------

SUITE_CASES = [
    ("scene = 5\n", "`scene` must be a list of [[scene]] tables (each with name and path), not int"),
    ('[scene]\nname = "a"\npath = "synthetic:ring"\n', "not one [scene] table"),
    ('[[scene]]\nname = "a"\npath = "synthetic:ring"\noptions = "x"\n', "scene 1: options must be a table, not 'x'"),
    ('[[scene]]\nname = 5\npath = "synthetic:ring"\n', "scene 1: name must be a string (not empty), not 5"),
    ('[[scene]]\nname = "a"\npath = "synthetic:ring"\nsmoke = "yes"\n', "scene 1: smoke must be true or false"),
    ('[[scene]]\nname = "a"\npaht = "synthetic:ring"\n', "scene 1 has an unknown key 'paht'"),
    ('[[scene]]\nname = "a"\npath = "synthetic:ring"\noptions = { x = [1] }\n', "option 'x' must be a string, number"),
    ('[[scene]]\nname = "caf\xe9"\n', "not UTF-8 text (byte 0xe9"),
]


@pytest.mark.parametrize("text,says", SUITE_CASES, ids=[str(i) for i in range(len(SUITE_CASES))])
def test_a_suite_of_the_wrong_shape_is_one_line(tmp_path, monkeypatch, text, says):
    suite = tmp_path / "suite.toml"
    suite.write_bytes(text.encode("latin-1"))
    with pytest.raises(SuiteError) as info:
        load_suite(str(suite))
    assert one_line(info.value).startswith(f"{suite}: ") and says in str(info.value)
    out = tmp_path / "out"
    line = hpgs_error(monkeypatch, "bench", "--suite", suite, "--out", out)
    assert says in line and not out.exists()


RESULT = REPO / "benchmarks" / "results" / "suite" / "juicebox" / "hpgs" / "farthest" / "seed3.json"
RESULT_CASES = [
    ("a list", lambda d: [d], "not a benchmark result (a JSON list, not an object)"),
    ("scene a number", lambda d: {**d, "scene": 5}, "not a benchmark result (scene is 5)"),
    ("psnr a string", lambda d: {**d, "test": {**d["test"], "psnr": "x"}}, "test metric psnr is 'x', not a number"),
    ("version a string", lambda d: {**d, "version": "2"}, "result version '2' is not one this hpgs_ns reads"),
    ("timing a list", lambda d: {**d, "timing": [1]}, "not a benchmark result (timing is [1])"),
    ("rounds of the wrong type", lambda d: {**d, "psnr_per_round": [1]}, "not a benchmark result (TypeError"),
    ("round steps not numbers", lambda d: {**d, "psnr_at_round_steps": {"a": 1}}, "not a benchmark result (ValueError"),
]


@pytest.mark.parametrize("change,says", [c[1:] for c in RESULT_CASES], ids=[c[0] for c in RESULT_CASES])
def test_a_bench_result_with_wrong_typed_fields_is_one_line(tmp_path, change, says):
    if not RESULT.is_file():
        pytest.skip(f"{RESULT} not found")
    data = RunResult.from_json(RESULT).to_dict()
    path = tmp_path / "seed3.json"
    path.write_text(json.dumps(change(data)))
    with pytest.raises(ResultError) as info:
        RunResult.from_json(path)
    assert one_line(info.value).startswith(f"{path}: ") and says in str(info.value)


def test_the_near_cull_count_is_written_only_where_a_run_recorded_it(tmp_path):
    from helpers import make_result

    counted = make_result(near_culled=42)
    assert RunResult.from_dict(json.loads(json.dumps(counted.to_dict()))).near_culled == 42
    plain = make_result().to_dict()
    assert "near_culled" not in plain and RunResult.from_dict(plain).near_culled is None
