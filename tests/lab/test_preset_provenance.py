"""A preset's options (its parts are nested configs) are recorded in a run's JSON as plain values."""

from __future__ import annotations

import json

from hpgs_lab.provenance import selector_options


def test_a_presets_nested_options_are_plain_json_with_their_flags_applied():
    options = selector_options("farthest-dopt", ["--pipeline.selection.farthest-dopt.then.probes", "2",
                                                 "--pipeline.selection.fisher.probes", "5"])
    assert json.loads(json.dumps(options)) == options  # no classes left in it
    assert options["then"]["probes"] == 2 and options["then"]["criterion"] == "dopt"
    assert options["first"] == {"tie_tolerance": 0.001} and options["shortlist_size"] == 0.2
    assert selector_options("fisher", ["--pipeline.selection.fisher.probes", "5"])["probes"] == 5
