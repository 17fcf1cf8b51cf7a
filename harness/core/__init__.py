"""The floor: what the simulator, the models and the rest of the harness all stand on.

    types     Sample, the one record a data set item is
    boxes     the LiDAR box row [x, y, z, l, w, h, yaw]: corners, IoU, NMS, points in boxes
    kitti     KITTI files (the only place KITTI's camera-frame boxes exist)
    files     atomic writes, their temp-file sweep, a folder lock, file hashes
    braking   the ego's stopping distance, shared by the scenario and the SOTIF verdict

It imports nothing of the project above it (tests/test_imports.py holds the rule), so models/ and
simulator/ may import it without reaching into the harness.
"""
