"""`hpgs bench` refuses a sweep whose `ns-train hpgs` arguments ns-train would refuse before it launches any run, in
one line naming the option and the reason (issue #65, item 5); a failed run's summary names the reason, not the
border of tyro's error box; the suite's lines for an unknown dataparser and an empty suite give the fix."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from hpgs_lab import runs
from hpgs_lab.names import FINAL_SET
from hpgs_lab.runs import Bench, Job
from hpgs_lab.suites import SuiteError, load_suite, scene_from_folder
from hpgs_ns.errors import UserError

BOX = "╭╮╰╯─│"

# the end of a run's log where ns-train refused an option of the scene's dataparser (UTF-8, as tyro writes a log)
REFUSED_LOG = """\
  @custom_bwd
╭─ Unrecognized options ───────────────────────────────────────────────────────╮
│ Unrecognized options: --nosuch-option, 1                                     │
│ ──────────────────────────────────────────────────────────────────────────── │
│ For full helptext, run                                                       │
│ /work/main/.venv/lib/python3.11/site-packages/nerfstudio/scripts/train.py    │
│ --help                                                                       │
╰──────────────────────────────────────────────────────────────────────────────╯
"""


@pytest.fixture
def launches(monkeypatch):
    """The commands the sweep launched (none should be) and how many parses the check made."""
    seen = {"launched": [], "parses": 0}

    def run_one(bench, job, *args, **kwargs):
        seen["launched"].append(job.label)
        raise AssertionError("a run was launched")

    parse = getattr(runs, "ns_train_refusal", None)

    def counted(args):
        seen["parses"] += 1
        return parse(args)

    monkeypatch.setattr(runs, "run_one", run_one)
    monkeypatch.setattr(runs, "ns_train_refusal", counted, raising=False)
    return seen


def bench(out: Path, **options) -> Bench:
    options = {"selectors": ["random", "farthest"], "seeds": [0, 1, 2], **options}
    return Bench(out=out, protocols=["fisherrf"], step_scale=0.01, rasterizer="cpu", initial_views=4, **options)


def one_line(message: str) -> str:
    assert "\n" not in message and not set(message) & set(BOX), message
    return message


def test_a_suite_option_the_dataparser_lacks_is_refused_before_any_run_launches(tiny_scene, tmp_path, launches):
    suite = tmp_path / "suite.toml"
    suite.write_text(f'[[scene]]\nname = "ring"\npath = "{tiny_scene.name}"\noptions = {{ nosuch-option = 1 }}\n')
    with pytest.raises(UserError) as caught:
        bench(tmp_path / "out", suite=str(suite), data_root=tiny_scene.parent).main()
    message = one_line(str(caught.value))
    assert message.startswith("hpgs bench: ring/fisherrf/random/seed0: ns-train hpgs refuses its arguments: "
                              "Unrecognized options: --nosuch-option; it is an option of scene 'ring' in the suite: "
                              "fix or drop it (`ns-train hpgs mipnerf360 --help` lists mipnerf360's options)"), message
    assert message.endswith("; no run was launched")
    assert launches == {"launched": [], "parses": 1}


def test_a_bad_value_and_a_bad_extra_argument_are_named_with_their_fix(tiny_scene, tmp_path, launches):
    with pytest.raises(UserError) as caught:
        bench(tmp_path / "a", scenes=[tiny_scene], extra_args="--pipeline.model.nosuch 3").main()
    assert "Unrecognized options: --pipeline.model.nosuch; it is in --extra-args: fix or drop it" in one_line(str(caught.value))
    with pytest.raises(UserError) as caught:  # a value a config's own check refuses: its line, with its fix
        bench(tmp_path / "b", scenes=[tiny_scene], downscale_factor=0).main()
    assert ("refuses its arguments: mipnerf360 --downscale-factor 0: must be at least 1; pass 1, 2, 4, ... or leave "
            "it out (automatic); it is an option of scene 'ring'") in one_line(str(caught.value))
    with pytest.raises(UserError) as caught:
        bench(tmp_path / "c", scenes=[tiny_scene], selectors=["random", "nosuch"]).main()
    assert "hpgs bench: --selectors nosuch: unknown selector; choose one of random, farthest" in one_line(str(caught.value))
    assert launches["launched"] == []


def test_arguments_are_parsed_once_per_shape_not_per_seed_or_selector(tiny_scene, tmp_path, launches):
    sweep = bench(tmp_path / "out")
    jobs = sweep.jobs([scene_from_folder(tiny_scene)])
    assert len(jobs) == 12  # 2 selectors and 2 reference rows, 3 seeds each
    jobs.append(Job(jobs[0].scene, jobs[0].protocol, FINAL_SET, 0, source="random", views=("images/0000.png",)))
    runs.check_commands(sweep, jobs)
    assert launches == {"launched": [], "parses": 2}  # the runs and references; the final-set, which names its views


def test_a_failed_runs_summary_names_the_reason_not_the_box_border(tiny_scene, tmp_path, monkeypatch):
    # a run whose ns-train exits with tyro's box at the end of its log
    fail = [sys.executable, "-c", f"import sys; sys.stdout.write({REFUSED_LOG!r}); sys.exit(2)"]
    monkeypatch.setattr(runs, "train_args", lambda *args: fail)
    sweep = bench(tmp_path / "out")
    job = sweep.jobs([scene_from_folder(tiny_scene)])[0]
    with pytest.raises(runs.TrainingFailed) as caught:
        runs.run_one(sweep, job)
    assert str(caught.value).startswith("hpgs bench: training ring/fisherrf/random/seed0 failed (Unrecognized options: "
                                        "--nosuch-option); its log: ")
    one_line(str(caught.value))
    assert runs.stop_reason(REFUSED_LOG.splitlines()) == "Unrecognized options: --nosuch-option"
    assert runs.stop_reason(["Traceback ...", "error: scene folder x does not exist; pass --data PATH", "│ x │"]) == \
        "error: scene folder x does not exist; pass --data PATH"
    assert runs.stop_reason(["Traceback (most recent call last):", "KeyError: 'means'"]) == "KeyError: 'means'"


def test_an_unknown_dataparser_lists_the_choices_and_an_empty_suite_gives_the_fix(tiny_scene, tmp_path):
    suite = tmp_path / "suite.toml"
    suite.write_text(f'[[scene]]\nname = "ring"\npath = "{tiny_scene.name}"\ndataparser = "nosuchparser"\n')
    with pytest.raises(SuiteError, match=r"scene 'ring': unknown dataparser 'nosuchparser'; choose one of mipnerf360, "
                                         r"nerfstudio-data, .*blender-data.* \(or leave dataparser out"):
        load_suite(str(suite), tiny_scene.parent)
    suite.write_text("# no scenes yet\n")
    with pytest.raises(SuiteError, match=r"suite.toml: no \[\[scene\]\] entries; add a \[\[scene\]\] table with a name "
                                         r"and a path for each scene \(e.g. .*real6.toml\)"):
        load_suite(str(suite))
