"""benchmarks/triangulation_variants.py, the triangulation variants `triangulation_yield.py` tried and the plugin
does not ship: guided matching's every-pair epipolar distance and its matches. (The shipped triangulation:
tests/plugin/test_triangulate.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO
from helpers import load_script, two_views_of_points

from hpgs_ns.scenes.triangulate import epipolar_distance


@pytest.fixture(scope="module")
def variants():
    return load_script(REPO / "benchmarks" / "triangulation_variants.py")


def test_guided_matching_keeps_mutual_nearest_descriptors_within_the_epipolar_band(variants):
    """Guided matching: its every-pair epipolar distance agrees with the package's on matched points, and only
    candidates within the band compete."""
    colmap_cameras, cam2_from_cam1, pixels = two_views_of_points()
    every = variants.epipolar_distance_matrix(*colmap_cameras, cam2_from_cam1, pixels[0], pixels[1])
    distance = epipolar_distance(*colmap_cameras, cam2_from_cam1, pixels[0], pixels[1])
    assert every.shape == (50, 50) and np.allclose(np.diag(every), distance, atol=1e-6)  # the diagonal: true matches
    rng = np.random.default_rng(1)
    descriptors = rng.integers(0, 255, (50, 128)).astype(np.uint8)
    noisy = np.clip(descriptors + rng.integers(-20, 20, (50, 128)), 0, 255).astype(np.uint8)
    matches = variants.guided_matches(descriptors, noisy, every, max_error=4.0, max_ratio=0.9)
    assert len(matches) >= 45 and (matches[:, 0] == matches[:, 1]).all()
    assert len(variants.guided_matches(descriptors, noisy, np.full((50, 50), np.inf), 4.0, 0.9)) == 0  # no band, no match
    assert variants.VariantSettings(verification="guided").verification == "guided"
