"""Fuzzing the CLI's file and argument paths: whatever bytes a label, calib, velodyne or prediction
file holds, and whatever a path argument says, the command ends with exit 0 or 2, never a traceback."""
import itertools

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from harness.cli import main
from harness.core import kitti
from tests.harness.conftest import centroid_detector, make_dataset

FIELD = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-5, 5).map(str),
                  st.sampled_from(["-1", "0", "1", "-10", "1e309", "-0.0", "x", ""]))
LINE = st.builds(lambda name, fields: " ".join([name, *fields]),
                 st.sampled_from([*kitti.KITTI_CLASSES, "car", "Foo"]), st.lists(FIELD, min_size=13, max_size=16))
# any bytes, and text that is nearly a KITTI file (right line shapes, odd values), which gets further in
CONTENT = st.one_of(st.binary(max_size=300),
                    st.lists(LINE, max_size=4).map(lambda lines: "\n".join(lines).encode()))
CALIB_KEYS = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")
CALIB = st.one_of(st.binary(max_size=300), st.lists(
    st.builds(lambda key, fields: f"{key}: " + " ".join(fields), st.sampled_from(CALIB_KEYS),
              st.lists(FIELD, min_size=9, max_size=12)), max_size=8).map(lambda lines: "\n".join(lines).encode()))
POINTS = st.one_of(st.binary(max_size=256), st.lists(st.floats(width=32), min_size=0, max_size=64).map(
    lambda v: __import__("numpy").asarray(v[: len(v) // 4 * 4], "<f4").tobytes()))
FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture])  # capsys and chdir hold for every example


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A two-frame data set, its labels as predictions, and a contract-conforming ONNX detector."""
    root = tmp_path_factory.mktemp("fuzz")
    data = make_dataset(root / "data", n_frames=2, cars=2)
    pred = root / "pred"
    for p in (data / "training" / "label_2").glob("*.txt"):
        lab = kitti.read_labels(p)
        lab.score = [0.5] * len(lab)
        kitti.write_labels(pred / p.name, lab)
    return {"root": root, "data": data, "pred": pred, "onnx": centroid_detector(root / "c.onnx"),
            "n": itertools.count()}


def _evaluate(world, labels, pred):
    return main(["--quiet", "evaluate", "--labels", str(labels), "--predictions", str(pred), "--bootstrap", "2",
                 "--output", str(world["root"] / "results.json")])


def _exit_ok(code, capsys):
    err = capsys.readouterr().err
    assert code in (0, 2) and "Traceback" not in err, err
    if code == 2:
        assert "error: " in err


@FUZZ
@given(content=CONTENT, as_labels=st.booleans())
def test_any_label_or_prediction_file(world, capsys, content, as_labels):
    folder = world["data"] / "training" / "label_2" if as_labels else world["pred"]
    target = folder / "000001.txt"
    keep = target.read_bytes()
    target.write_bytes(content)
    try:
        _exit_ok(_evaluate(world, world["data"], world["pred"]), capsys)
    finally:
        target.write_bytes(keep)


@FUZZ
@given(content=st.one_of(CALIB, POINTS), kind=st.sampled_from(["calib", "velodyne"]))
def test_any_calib_or_velodyne_file(world, capsys, content, kind):
    target = kitti.frame_path(world["data"], kind, "000001")
    keep = target.read_bytes()
    target.write_bytes(content)
    out = world["root"] / f"predict{next(world['n'])}"
    try:
        _exit_ok(main(["--quiet", "predict", "--onnx", str(world["onnx"]), "--data", str(world["data"]),
                       "--out", str(out)]), capsys)
    finally:
        target.write_bytes(keep)


PATH = st.one_of(st.text(max_size=20), st.sampled_from(["", ".", "/", "-", "data", "pred/000000.txt",
                                                         "c.onnx", "data/ImageSets/test.txt", "\0"]))


# outputs stay inside the test's folder (the suite may run as root: no write into a system folder)
OUTPUT = st.one_of(st.text(max_size=20).map(lambda t: "out_" + t.replace("/", "_")),
                   st.sampled_from(["", ".", "data", "pred", "pred/000000.txt", "c.onnx", "data/ImageSets/test.txt",
                                    "out_dir/", "\0"]))


@FUZZ
@given(labels=PATH, pred=PATH, split=PATH, output=OUTPUT)
def test_any_path_arguments(world, capsys, monkeypatch, labels, pred, split, output):
    monkeypatch.chdir(world["root"])
    args = ["--quiet", "evaluate", "--labels", labels, "--predictions", pred, "--split", split, "--bootstrap", "2",
            "--output", output or "r.json"]
    try:
        code = main(args)
    except SystemExit as e:  # argparse refuses an argument that looks like an option: its usage error, exit 2
        code = e.code
    _exit_ok(code, capsys)
