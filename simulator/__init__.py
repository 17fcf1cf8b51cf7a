"""Ray-casting simulator of the SOTIF highway use case, writing KITTI data sets.

    from simulator import generate, WEATHER_PRESETS
    generate(Path("data/sotif"), preset="sotif", workers=2)        # 547 frames, 21 weathers
    generate(Path("data/train"), preset="train", frames=400)       # dry presets by default
    generate(Path("data/space"), preset="sotif", instances=32)     # 32 cut-out instances per weather

Modules (data flows top to bottom):
    weather    the 21 CARLA presets and the physical quantities derived from them
    road, world, prims, materials   procedural highway (lanes, markings, barriers, poles,
               signs, terrain, vegetation) as one triangle soup with materials
    vehicles   six procedural body types (Car / Van / Truck labels)
    scenario   the SOTIF cut-out scenario (ACC ego, fast car overtaking a slow car), its braking
               rule and decision window, and randomised training traffic
    space      the scenario space: seeded Latin-hypercube instances, paint reflectances, sweep weather
    raycast    Embree: static world BVH once per process + per-frame vehicle BVH
    effects    published weather models for the LiDAR, one function each
    lidar      LidarSpec (HDL-64E-like default, CARLA mode), scan -> (N, 4) points
    camera     ray-cast front camera with KITTI P2 intrinsics
    labels     KITTI labels: 3D/2D boxes, truncation, occlusion, DontCare
    frame, dataset   one frame to files; the data set with resume, hashes and meta
    export     PLY export for MeshLab and a BEV + image preview figure
"""
from simulator.dataset import generate
from simulator.weather import WEATHER_PRESETS

__all__ = ["WEATHER_PRESETS", "generate"]
