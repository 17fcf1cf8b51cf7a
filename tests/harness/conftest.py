"""Tiny KITTI data sets and contract-conforming ONNX files made by the tests themselves."""
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from harness.core import kitti
from harness.core.kitti import Labels


def car_boxes(rng, n):
    """(n, 7) LiDAR boxes of cars ahead, spread over 5-70 m."""
    return np.c_[rng.uniform(5, 70, n), rng.uniform(-8, 8, n), np.full(n, -0.9), rng.uniform(3.8, 4.6, n),
                 rng.uniform(1.6, 1.9, n), rng.uniform(1.4, 1.6, n), rng.uniform(-0.2, 0.2, n)].astype(np.float32)


def make_dataset(root, n_frames=6, cars=3, seed=0, weathers=("ClearNoon", "HardRainNight")):
    """A KITTI layout with points on the car boxes, labels, calib, ImageSets and meta."""
    rng = np.random.default_rng(seed)
    calib = kitti.kitti_calib()
    rows = []
    for i in range(n_frames):
        fid = f"{i:06d}"
        boxes = car_boxes(rng, cars)
        pts = [np.c_[rng.uniform(-0.5, 0.5, (200, 3)) * b[3:6] + b[:3], rng.uniform(0, 1, 200)] for b in boxes]
        points = np.concatenate(pts + [np.c_[rng.uniform(0, 80, (500, 1)), rng.uniform(-20, 20, (500, 1)),
                                             np.full((500, 1), -1.73), rng.uniform(0, 1, (500, 1))]]).astype(np.float32)
        kitti.write_points(kitti.frame_path(root, "velodyne", fid), points)
        kitti.write_calib(kitti.frame_path(root, "calib", fid), calib)
        kitti.write_labels(kitti.frame_path(root, "label_2", fid), Labels.from_lidar(boxes, calib, ["Car"] * cars))
        kitti.write_image(kitti.frame_path(root, "image_2", fid), np.zeros((375, 1242, 3), np.uint8))
        rows.append({"frame_id": fid, "split": "test", "weather": weathers[i % len(weathers)]})
    ids = [r["frame_id"] for r in rows]
    kitti.write_image_set(root / "ImageSets" / "test.txt", ids)
    import pandas as pd
    kitti.write_frames_meta(root / "meta" / "frames.csv", pd.DataFrame(rows))
    return root


def centroid_detector(path, metadata=None, drop_output=None, custom_op=False, two_stage=False):
    """A contract-conforming ONNX 'detector': one car box at the centroid of the points."""
    nodes = [
        helper.make_node("ReduceMean", ["points", "axes0"], ["centre"], keepdims=1),
        helper.make_node("Slice", ["centre", "s0", "s3", "ax1"], ["xyz"]),
        helper.make_node("Concat", ["xyz", "dims"], ["boxes"], axis=1),
        helper.make_node("Identity", ["score_c"], ["scores"]),
    ]
    inits = [helper.make_tensor("axes0", TensorProto.INT64, [1], [0]),
             helper.make_tensor("s0", TensorProto.INT64, [1], [0]), helper.make_tensor("s3", TensorProto.INT64, [1], [3]),
             helper.make_tensor("ax1", TensorProto.INT64, [1], [1]),
             helper.make_tensor("dims", TensorProto.FLOAT, [1, 4], [4.0, 1.8, 1.5, 0.0]),
             helper.make_tensor("score_c", TensorProto.FLOAT, [1], [0.9])]
    outputs = [helper.make_tensor_value_info("boxes", TensorProto.FLOAT, ["M", 7]),
               helper.make_tensor_value_info("scores", TensorProto.FLOAT, ["M"])]
    if two_stage:
        nodes += [helper.make_node("Identity", ["boxes"], ["rois"]), helper.make_node("Identity", ["scores"], ["roi_scores"])]
        outputs += [helper.make_tensor_value_info("rois", TensorProto.FLOAT, ["K", 7]),
                    helper.make_tensor_value_info("roi_scores", TensorProto.FLOAT, ["K"])]
    if custom_op:
        nodes.append(helper.make_node("Voxelize", ["points"], ["vox"], domain="my.ops"))
    if drop_output:
        outputs = [o for o in outputs if o.name != drop_output]
    graph = helper.make_graph(nodes, "centroid", [helper.make_tensor_value_info("points", TensorProto.FLOAT, ["N", 4])],
                              outputs, inits)
    opsets = [helper.make_opsetid("", 18)] + ([helper.make_opsetid("my.ops", 1)] if custom_op else [])
    model = helper.make_model(graph, opset_imports=opsets)
    meta = {"sotif.contract": "1", "sotif.architecture": "centroid", "sotif.classes": "Car",
            "sotif.point_cloud_range": "[0, -40, -3, 70.4, 40, 1]", "sotif.data_hash": "", "sotif.config_hash": ""} \
        if metadata is None else metadata
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, str(path))
    return path


@pytest.fixture
def dataset(tmp_path):
    return make_dataset(tmp_path / "data")


@pytest.fixture
def make_onnx():
    """Factory: ``make_onnx(path, **kwargs)`` writes a centroid detector (see centroid_detector)."""
    return centroid_detector
