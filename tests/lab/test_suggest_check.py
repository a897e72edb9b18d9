"""benchmarks/suggest_check.py, the withheld-arc check of `hpgs suggest`'s poses: how it cuts a capture into arcs
and height bands to withhold, and which withheld photo stands in for each suggestion. (`hpgs suggest` itself:
tests/plugin/test_suggest.py.)"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import REPO, model_trainer
from helpers import load_script


@pytest.fixture(scope="module")
def check():
    return load_script(REPO / "benchmarks" / "suggest_check.py")


def look_at(centre: torch.Tensor) -> torch.Tensor:
    """A nerfstudio camera-to-world [3, 4] at `centre` looking at the origin, z up."""
    back = centre / centre.norm()
    right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back), dim=0)
    return torch.stack([right, torch.linalg.cross(back, right), back, centre], dim=1)


def test_arcs_and_the_photos_nearest_to_suggestions(check, tiny_scene, tmp_path):
    cameras = model_trainer(tiny_scene, tmp_path).pipeline.datamanager.train_dataset.cameras
    blocks = check.arc_blocks(cameras, 3, 60.0)
    assert len(blocks) == 3 and all(5 <= len(b) <= 7 for b in blocks)  # 35 views on a ring: 60 of 360 degrees each
    assert not set(blocks[0]) & set(blocks[1])
    block = blocks[1]
    c2w = cameras.camera_to_worlds[block]
    at = [torch.cat([c2w[j], torch.tensor([[0, 0, 0, 1.0]])]).tolist() for j in (2, 2)]
    taken = check.nearest_photos(at, c2w, block)
    # the second suggestion sits on a photo already taken: it gets that photo's nearest neighbour in the block
    d = (c2w[:, :3, 3] - c2w[2, :3, 3]).norm(dim=1)
    d[2] = float("inf")
    assert taken == [block[2], block[int(d.argmin())]]


def test_arcs_spread_over_the_span_a_partial_capture_covers(check):
    from nerfstudio.cameras.cameras import Cameras

    # 30 cameras over 120 degrees of azimuth (a table-top phone capture), 0.5 above the object, looking at it.
    c2w = [look_at(torch.tensor([3 * math.cos(a), 3 * math.sin(a), 0.5]))
           for a in (math.radians(40 + 4 * k) for k in range(30))]
    cameras = Cameras(camera_to_worlds=torch.stack(c2w), fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
    blocks = check.arc_blocks(cameras, 3, 60.0)
    assert [len(b) for b in blocks] == [10, 10, 10]  # three 40-degree thirds of the span, none empty
    assert blocks[0] == list(range(10)) or blocks[0] == list(range(20, 30))  # contiguous, from one end
    assert not set(blocks[0]) & set(blocks[1]) and not set(blocks[1]) & set(blocks[2])
    assert check.capture_azimuths(cameras).numel() == 30


def test_a_higher_pass_is_withheld_as_a_band_and_one_continuous_band_is_not(check):
    from nerfstudio.cameras.cameras import Cameras

    def ring(count: int, elevations) -> Cameras:
        """`count` cameras at distance 3 looking at the origin, the k-th at azimuth 360k/count, elevation e_k."""
        c2w = []
        for k, e in zip(range(count), elevations):
            a, e = math.radians(360 * k / count), math.radians(e)
            c2w.append(look_at(torch.tensor([3 * math.cos(a) * math.cos(e), 3 * math.sin(a) * math.cos(e), 3 * math.sin(e)])))
        return Cameras(camera_to_worlds=torch.stack(c2w), fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)

    # a low ring of 24 at 5 degrees and a higher pass of 12 at 40 (interleaved in capture order)
    two = ring(36, [40.0 if k % 3 == 0 else 5.0 for k in range(36)])
    assert check.height_band(two, 10.0, 5) == [k for k in range(36) if k % 3 == 0]
    assert check.height_band(two, 40.0, 5) == []  # the gap (~35 degrees) is narrower than asked
    # a spiral from 5 to 45 degrees: no gap of 10 degrees anywhere, so no band
    spiral = ring(36, [5 + 40 * k / 35 for k in range(36)])
    assert check.height_band(spiral, 10.0, 5) == []
    assert check.capture_elevations(spiral).numel() == 36
