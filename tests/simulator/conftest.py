import numpy as np
import pytest

from simulator.raycast import RayScene
from simulator.road import RoadConfig
from simulator.world import build_world


@pytest.fixture(scope="session")
def highway_scene():
    """The full highway world (built once per test session)."""
    return RayScene(build_world(RoadConfig(), np.random.default_rng(0)))
