"""Shared fixtures of the model tests.

Test modules are imported with ``--import-mode=importlib``, so shared helpers reach them as
fixtures (each returning the helper function) rather than as imports.
"""
import numpy as np
import pytest
import torch

from harness.core.types import Sample

CARS = np.array([[10.0, 2.0, -0.95, 4.5, 1.8, 1.6, 0.1], [18.0, -4.0, -0.95, 4.2, 1.7, 1.5, -0.2]],
                np.float32)  # two cars, LiDAR-frame box rows


@pytest.fixture
def one_thread():
    """Tiny tensors on a shared 2-core machine: one intra-op thread avoids contention.

    Modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _two_car_scene(rng: np.random.Generator, ground: int = 3000, per_car: int = 300) -> Sample:
    """A ground plane 1.73 m below the sensor and points filling the two ``CARS`` boxes."""
    floor = np.c_[rng.uniform(0, 25, ground), rng.uniform(-12, 12, ground),
                  rng.normal(-1.73, 0.02, ground), rng.uniform(0, 1, ground)]
    parts = [floor]
    for b in CARS:
        local = rng.uniform(-0.5, 0.5, (per_car, 3)) * b[3:6]
        c, s = np.cos(b[6]), np.sin(b[6])
        xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + b[:2]
        parts.append(np.c_[xy, local[:, 2] + b[2], rng.uniform(0, 1, per_car)])
    points = np.concatenate(parts).astype(np.float32)
    return Sample("000000", points, CARS.copy(), np.array(["Car", "Car"]))


def _random_cloud(rng: np.random.Generator, pc_range, n: int) -> np.ndarray:
    """(n, 4) float32 points uniform over the range (a margin outside it included)."""
    lo, hi = np.array(pc_range[:3]) - 1.0, np.array(pc_range[3:]) + 1.0
    return np.c_[rng.uniform(lo, hi, (n, 3)), rng.uniform(0, 1, n)].astype(np.float32)


def _train_steps(model: torch.nn.Module, sample: Sample, steps: int) -> tuple[float, float]:
    """Adam steps on one frame; mean total loss of the first two and of the last two steps."""
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    totals = []
    for _ in range(steps):
        loss = model.loss([sample])["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        totals.append(float(loss.detach()))
    return float(np.mean(totals[:2])), float(np.mean(totals[-2:]))

def _no_box_on_empty_cloud(model: torch.nn.Module, onnx_path) -> None:
    """A two-stage model's RoIs of an empty cloud pooled nothing: no refined box, in torch and in
    onnxruntime."""
    from models.export import run_onnx
    empty = np.zeros((0, 4), np.float32)
    with torch.no_grad():
        boxes, scores, rois, roi_scores, _ = model(torch.from_numpy(empty))
    assert len(rois) > 0 and len(boxes) == 0 and len(scores) == 0
    assert len(run_onnx(onnx_path, empty)[0]) == 0


def _random_boxes(rng: np.random.Generator, k: int, spread: float = 20.0) -> np.ndarray:
    """(k, 7) float32 car-sized boxes, centres uniform in a cube of half-width ``spread``, any yaw."""
    centre = rng.uniform(-spread, spread, (k, 3))
    size = rng.uniform([3.0, 1.5, 1.3], [5.0, 2.2, 1.9], (k, 3))
    yaw = rng.uniform(-np.pi, np.pi, (k, 1))
    return np.concatenate([centre, size, yaw], 1).astype(np.float32)


@pytest.fixture(scope="session")
def random_boxes():
    """``random_boxes(rng, k, spread=20.0) -> (k, 7) float32`` car-sized boxes with any yaw."""
    return _random_boxes


@pytest.fixture
def two_car_scene():
    """``two_car_scene(rng, ground=3000, per_car=300) -> Sample``: ground plane + two cars."""
    return _two_car_scene


@pytest.fixture(scope="session")
def random_cloud():
    """``random_cloud(rng, pc_range, n) -> (n, 4) float32`` uniform over the range + 1 m."""
    return _random_cloud


@pytest.fixture
def train_steps():
    """``train_steps(model, sample, steps) -> (first loss, last loss)``: Adam on one frame."""
    return _train_steps


@pytest.fixture
def no_box_on_empty_cloud():
    """``no_box_on_empty_cloud(model, onnx_path)``: asserts the RoIs of an empty cloud give no box."""
    return _no_box_on_empty_cloud


@pytest.fixture(scope="session")
def simulated_frame() -> np.ndarray:
    """(N, 4) float32 one scan of the simulator's highway (about 110k points; ~20 s, once)."""
    from simulator.lidar import LidarSpec, scan
    from simulator.raycast import RayScene
    from simulator.road import RoadConfig
    from simulator.scenario import training_scene
    from simulator.weather import WEATHER_PRESETS
    from simulator.world import build_world

    road, rng = RoadConfig(), np.random.default_rng(0)
    scene = RayScene(build_world(road, np.random.default_rng(0)))
    state = training_scene(road, rng)
    scene.set_vehicles(state.vehicles)
    return scan(scene, LidarSpec(), state.pose, WEATHER_PRESETS["ClearNoon"], state.vehicles, rng)
