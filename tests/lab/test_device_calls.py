"""scripts/device_calls.py: what each device call carries stays under the limit, and everything travels once."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import load_script

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "device_calls.py"
MIB = 2**20


@pytest.fixture(scope="module")
def calls():
    return load_script(SCRIPT)


def test_every_call_fits_and_every_path_travels_once(calls):
    sizes = {"w": 36 * MIB, "vgg.0": 28 * MIB, "vgg.1": 28 * MIB, "vgg.sha": 4096, "pyco.0": 18 * MIB,
             "pyco.1": 18 * MIB, "pyco.sha": 4096, "alex": 9 * MIB, **{f"scene{i}": (i + 2) * MIB for i in range(8)}}
    units = [("vgg.0", "vgg.sha"), ("vgg.1", "vgg.sha"), ("pyco.0", "pyco.sha"), ("pyco.1", "pyco.sha"), ("alex",),
             *[(f"scene{i}",) for i in range(8)]]
    tree, limit = 27 * MIB, 63 * MIB
    out = calls.pack(tree, limit, ("w",), units, sizes)
    assert out[0][0] == "w"
    for carry in out:
        assert len(carry) == len(set(carry))  # a checksum two halves share is carried once per call
        assert tree + sum(sizes[p] for p in carry) <= limit
    carried = [p for carry in out for p in carry]
    assert sorted(set(carried)) == sorted(sizes)
    assert sum(p != "vgg.sha" and p != "pyco.sha" for p in carried) == len(sizes) - 2  # each other path once
    # the two VGG halves cannot share a call beside this tree; the largest units go first
    assert not any({"vgg.0", "vgg.1"} <= set(carry) for carry in out)
    assert len(out) == 6


def test_a_unit_that_cannot_fit_any_call_is_named(calls):
    with pytest.raises(calls.CallsError, match="big .40.0 MiB. does not fit a call beside the working tree .27.0 MiB."):
        calls.pack(27 * MIB, 63 * MIB, ("w",), [("big",)], {"w": MIB, "big": 40 * MIB})
    with pytest.raises(calls.CallsError, match="w with the working tree is 67.0 MiB"):
        calls.pack(27 * MIB, 63 * MIB, ("w",), [], {"w": 40 * MIB})
