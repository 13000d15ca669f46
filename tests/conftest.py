"""Shared test settings: hypothesis profiles (CI runs the 'ci' profile, deterministic)."""

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    max_examples=200,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", max_examples=100, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture
def map_file(tmp_path):
    """A small valid lawn map file (an ellipse, six landmarks), for the map tools' tests."""
    import numpy as np

    from mowerhw.map import Landmark, LawnMap

    a = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    m = LawnMap(
        boundary=np.column_stack([6 * np.cos(a), 4 * np.sin(a)]),
        landmarks=[
            Landmark(i, np.array([8.0 * np.cos(i), 8.0 * np.sin(i), 1.0]), np.eye(3) * 1e-4)
            for i in range(6)
        ],
    )
    path = tmp_path / "lawn.json"
    m.save(path)
    return path
