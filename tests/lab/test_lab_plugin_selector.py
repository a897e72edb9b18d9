"""A selector another package registers reaches the lab: `hpgs bench`'s rows and the code hash of its runs."""

from __future__ import annotations

from conftest import TOY

from hpgs_lab.protocols import row_order
from hpgs_lab.provenance import code_hash
from hpgs_ns.selectors.registry import BUILTIN_SELECTORS


def test_a_plugin_selector_reaches_the_bench_rows_and_provenance(toy_plugin):
    assert row_order().index("last") == len(BUILTIN_SELECTORS)  # after the built-in ones, before the references
    before = code_hash("last")
    assert before != code_hash(None)
    (toy_plugin / "toy_selector.py").write_text(TOY + "\nCHANGED = 1  # a change to the plugin's module\n")
    assert code_hash("last") != before  # the plugin's own file moves its runs' code hash
