"""KITTI files: velodyne scans, label_2 lines, calib files, images, ImageSets and frame meta.

This is the only place where KITTI's camera-frame box convention (bottom-centre location,
``h w l``, ``rotation_y = -yaw - pi/2``) exists; everything else uses the LiDAR box row of
``harness.core.types``. Every reader raises ``KittiError`` naming the file (and line) on bad input;
every writer is atomic (``harness.core.files``: temp file + rename), so an interrupted write never
leaves half a file.
"""
from __future__ import annotations

import io
import math
from contextlib import contextmanager
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

from harness.core.boxes import corners_3d, wrap_angle
from harness.core.files import atomic_write_bytes, atomic_write_text

KITTI_CLASSES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram",
                 "Misc", "DontCare")
KINDS = {"velodyne": ".bin", "image_2": ".png", "calib": ".txt", "label_2": ".txt"}
IMAGE_SIZE = (1242, 375)  # (width, height) of KITTI's left colour camera


class KittiError(ValueError):
    """A KITTI file is missing or malformed. The message names the file (and line)."""

    def __init__(self, path, problem: str, line: int | None = None):
        where = f"{path}:{line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {problem}")
        self.path, self.line, self.problem = Path(path), line, problem

    def __reduce__(self):  # pickled whole (a job process of `run` raises it in the run's process)
        return type(self), (self.path, self.problem, self.line)


def frame_path(root, kind: str, frame_id: str, split_dir: str = "training") -> Path:
    """``<root>/training/<kind>/<frame_id>.<ext>``."""
    if kind not in KINDS:
        raise ValueError(f"unknown KITTI folder {kind!r}; expected one of {sorted(KINDS)}")
    return Path(root) / split_dir / kind / f"{frame_id}{KINDS[kind]}"


def _read_text(path) -> str:
    path = Path(path)
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise KittiError(path, "file not found") from None
    except IsADirectoryError:
        raise KittiError(path, "is a folder, not a file") from None
    except UnicodeDecodeError as e:
        raise KittiError(path, f"not a text file ({e.reason})") from None


# ----------------------------------------------------------------------------- velodyne
def read_points(path) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity from a velodyne ``.bin`` file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise KittiError(path, "file not found") from None
    if len(raw) % 16:
        raise KittiError(path, f"size {len(raw)} bytes is not a multiple of 16 (4 float32 per point);"
                               " the file is truncated or not a velodyne scan")
    points = np.frombuffer(raw, dtype="<f4").reshape(-1, 4).astype(np.float32)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise KittiError(path, f"{int(bad.sum())} points contain NaN or inf (first at point {int(np.argmax(bad))})")
    bad = (np.abs(points) > MAX_POINT_VALUE).any(axis=1)
    if bad.any():  # sums over such values overflow float32 inside a network: boxes vanish without an error
        i = int(np.argmax(bad))
        raise KittiError(path, f"{int(bad.sum())} points hold a value beyond +-{MAX_POINT_VALUE:g} (first: point {i}, "
                               f"{' '.join(f'{v:g}' for v in points[i])}): not metres and a LiDAR intensity")
    return points


def write_points(path, points: np.ndarray) -> Path:
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"{path}: points must be (N, 4), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{path}: refusing to write NaN or inf points")
    return atomic_write_bytes(path, points.astype("<f4").tobytes())


# ----------------------------------------------------------------------------- calib
_CALIB_SHAPES = {"P0": (3, 4), "P1": (3, 4), "P2": (3, 4), "P3": (3, 4), "R0_rect": (3, 3),
                 "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4)}
_CALIB_REQUIRED = ("P2", "R0_rect", "Tr_velo_to_cam")
MAX_POINT_VALUE = 1e6  # |x|, |y|, |z| in metres and |intensity| of any real scan are far below it
ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| of a calib's rotation (KITTI's own files: about 1e-6)


def _hom(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


@dataclass
class Calib:
    """KITTI calibration. Points: LiDAR -> (Tr_velo_to_cam) camera -> (R0_rect) rectified -> (P2) image."""

    P2: np.ndarray
    R0_rect: np.ndarray = field(default_factory=lambda: np.eye(3))
    Tr_velo_to_cam: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)))
    P0: np.ndarray | None = None
    P1: np.ndarray | None = None
    P3: np.ndarray | None = None
    Tr_imu_to_velo: np.ndarray | None = None

    def velo_to_rect(self) -> np.ndarray:
        """(4, 4) homogeneous LiDAR -> rectified camera."""
        return _hom(self.R0_rect) @ _hom(self.Tr_velo_to_cam)

    def lidar2img(self) -> np.ndarray:
        """(4, 4) float32 P2 @ R0_rect @ Tr_velo_to_cam (the ONNX contract's ``lidar2img``)."""
        return (_hom(self.P2) @ self.velo_to_rect()).astype(np.float32)

    def lidar_to_rect(self, pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        return pts @ self.velo_to_rect()[:3, :3].T + self.velo_to_rect()[:3, 3]

    def rect_to_lidar(self, pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        inv = np.linalg.inv(self.velo_to_rect())
        return pts @ inv[:3, :3].T + inv[:3, 3]

    def project_rect(self, pts_rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified camera points (N, 3) -> pixel (N, 2) and depth (N,)."""
        pts_rect = np.asarray(pts_rect, dtype=np.float64).reshape(-1, 3)
        uvw = pts_rect @ self.P2[:, :3].T + self.P2[:, 3]
        depth = uvw[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / depth[:, None]
        return uv, depth

    def project_lidar(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LiDAR points (N, 3) -> pixel (N, 2) and depth (N,) in front of the camera."""
        return self.project_rect(self.lidar_to_rect(pts))


def kitti_calib(width: int = IMAGE_SIZE[0], height: int = IMAGE_SIZE[1], focal: float = 721.5377,
                cam_in_lidar=(0.27, 0.0, -0.08)) -> Calib:
    """A KITTI-like calib for a forward camera at ``cam_in_lidar`` (metres, LiDAR frame).

    Defaults are KITTI's: P2 focal 721.5 px, camera 0.27 m ahead of and 0.08 m below the LiDAR.
    """
    rot = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # lidar -> camera axes
    tr = np.hstack([rot, (-rot @ np.asarray(cam_in_lidar, dtype=np.float64))[:, None]])
    cx, cy = width / 2.0 - 0.5, height / 2.0 - 0.5
    p = np.array([[focal, 0.0, cx, 0.0], [0.0, focal, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return Calib(P2=p, R0_rect=np.eye(3), Tr_velo_to_cam=tr, P0=p.copy(), P1=p.copy(), P3=p.copy(),
                 Tr_imu_to_velo=np.hstack([np.eye(3), np.zeros((3, 1))]))


def read_calib(path) -> Calib:
    path = Path(path)
    values: dict[str, np.ndarray] = {}
    for no, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep:
            raise KittiError(path, f"expected 'KEY: numbers', got {line[:60]!r}", no)
        if key == "Tr_velo_cam":  # spelling of some KITTI tracking files
            key = "Tr_velo_to_cam"
        if key == "R_rect":
            key = "R0_rect"
        shape = _CALIB_SHAPES.get(key)
        if shape is None:
            continue  # other sensors' keys are allowed and ignored
        try:
            nums = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise KittiError(path, f"{key}: not a list of numbers", no) from None
        if nums.size != shape[0] * shape[1]:
            raise KittiError(path, f"{key}: expected {shape[0] * shape[1]} numbers, got {nums.size}", no)
        if not np.isfinite(nums).all():
            raise KittiError(path, f"{key}: contains NaN or inf", no)
        values[key] = nums.reshape(shape)
    missing = [k for k in _CALIB_REQUIRED if k not in values]
    if missing:
        raise KittiError(path, f"missing calib key(s) {', '.join(missing)}")
    for key in _CALIB_REQUIRED:  # each must map 3D points one to one (rotation / intrinsics part)
        rank = int(np.linalg.matrix_rank(values[key][:, :3]))
        if rank < 3:
            raise KittiError(path, f"{key}: singular (its 3x3 part has rank {rank}), so it maps points onto a "
                                   f"{'plane' if rank == 2 else 'line or point'}")
    for key in ("R0_rect", "Tr_velo_to_cam"):  # rigid: a rotation (KITTI's to ~1e-6), no scale
        r = values[key][:, :3]
        off = float(np.abs(r.T @ r - np.eye(3)).max())
        if off > ROTATION_TOLERANCE:
            raise KittiError(path, f"{key}: its 3x3 part is not a rotation (R^T R differs from the identity by up to "
                                   f"{off:.3g}), so it would scale or shear every box")
    return Calib(**values)


def write_calib(path, calib: Calib) -> Path:
    lines = []
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        m = getattr(calib, key)
        if m is None:
            m = calib.P2 if key.startswith("P") else np.hstack([np.eye(3), np.zeros((3, 1))])
        lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in np.asarray(m, dtype=np.float64).ravel()))
    return atomic_write_text(path, "\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- labels
@dataclass
class Labels:
    """The objects of one label_2 file (ground truth) or result file (with ``score``)."""

    name: np.ndarray  # (K,) str
    truncated: np.ndarray  # (K,) float, 0..1
    occluded: np.ndarray  # (K,) int, 0..3
    alpha: np.ndarray  # (K,) float, observation angle, rad
    bbox: np.ndarray  # (K, 4) float, left top right bottom, px
    dimensions: np.ndarray  # (K, 3) float, h w l, m
    location: np.ndarray  # (K, 3) float, bottom centre in the rectified camera frame, m
    rotation_y: np.ndarray  # (K,) float, rad
    score: np.ndarray | None = None  # (K,) float, results only

    def __len__(self) -> int:
        return len(self.name)

    @classmethod
    def empty(cls, with_score: bool = False) -> "Labels":
        return cls(np.zeros(0, dtype=object), np.zeros(0), np.zeros(0, dtype=int), np.zeros(0),
                   np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0),
                   np.zeros(0) if with_score else None)

    def select(self, mask) -> "Labels":
        return Labels(**{f.name: (None if getattr(self, f.name) is None else getattr(self, f.name)[mask])
                         for f in fields(self)})

    @classmethod
    def from_lidar(cls, boxes, calib: Calib, names, bbox=None, truncated=None, occluded=None,
                   score=None, image_size=IMAGE_SIZE) -> "Labels":
        """KITTI labels from LiDAR boxes (K, 7); 2D boxes projected and clipped when not given."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
        k = len(boxes)
        bottom = boxes[:, :3] - np.c_[np.zeros((k, 2)), boxes[:, 5] / 2]
        loc = calib.lidar_to_rect(bottom)
        ry = wrap_angle(-boxes[:, 6] - np.pi / 2)
        alpha = wrap_angle(ry - np.arctan2(loc[:, 0], loc[:, 2]))
        if bbox is None:
            bbox = project_boxes_2d(boxes, calib, image_size)
        return cls(name=np.asarray(names, dtype=object).reshape(k),
                   truncated=np.zeros(k) if truncated is None else np.asarray(truncated, float),
                   occluded=np.zeros(k, int) if occluded is None else np.asarray(occluded, int),
                   alpha=alpha, bbox=np.asarray(bbox, float).reshape(k, 4),
                   dimensions=boxes[:, [5, 4, 3]], location=loc, rotation_y=ry,
                   score=None if score is None else np.asarray(score, float).reshape(k))

    def to_lidar(self, calib: Calib) -> np.ndarray:
        """(K, 7) float32 LiDAR boxes [x, y, z, l, w, h, yaw] (geometric centre)."""
        h, w, l = self.dimensions.T
        centre = calib.rect_to_lidar(self.location) + np.c_[np.zeros((len(self), 2)), h / 2]
        yaw = wrap_angle(-self.rotation_y - np.pi / 2)
        return np.c_[centre, l, w, h, yaw].astype(np.float32)


def project_boxes_2d(boxes, calib: Calib, image_size=IMAGE_SIZE) -> np.ndarray:
    """(K, 4) image boxes of LiDAR boxes: projected corners' extent clipped to the image.

    Corners behind the camera are clipped to a near plane first, so a box reaching past the
    camera still gets a finite 2D box. Boxes entirely behind the camera get a zero-size box.
    """
    corners = corners_3d(np.asarray(boxes, dtype=np.float64).reshape(-1, 7))  # (K, 8, 3) LiDAR
    rect = calib.lidar_to_rect(corners.reshape(-1, 3)).reshape(-1, 8, 3)
    out = np.zeros((len(rect), 4))
    for i, c in enumerate(rect):
        if (c[:, 2] <= 0.1).all():
            continue
        c = c.copy()
        c[:, 2] = np.maximum(c[:, 2], 0.1)
        uv, _ = calib.project_rect(c)
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        out[i] = [np.clip(lo[0], 0, image_size[0] - 1), np.clip(lo[1], 0, image_size[1] - 1),
                  np.clip(hi[0], 0, image_size[0] - 1), np.clip(hi[1], 0, image_size[1] - 1)]
    return out


def _parse_label_line(path, no: int, line: str, with_score: bool | None):
    parts = line.split()
    if len(parts) not in (15, 16):
        raise KittiError(path, f"expected 15 fields (16 with score), got {len(parts)}", no)
    if with_score is True and len(parts) != 16:
        raise KittiError(path, "result line without a score (16th field)", no)
    name = parts[0]
    if name not in KITTI_CLASSES:
        raise KittiError(path, f"unknown class {name!r}; expected one of {', '.join(KITTI_CLASSES)}", no)
    try:
        nums = [float(v) for v in parts[1:]]
    except ValueError:
        raise KittiError(path, "fields 2-15 must be numbers", no) from None
    if not all(math.isfinite(v) for v in nums):
        raise KittiError(path, "contains NaN or inf", no)
    if nums[1] != int(nums[1]) or not -1 <= nums[1] <= 3:
        raise KittiError(path, f"occluded must be an integer in -1..3, got {parts[2]}", no)
    return name, nums


def read_labels(path, with_score: bool | None = None) -> Labels:
    """Read a label_2 (15 fields) or result file (16 fields: + score).

    ``with_score=True`` requires scores (result files), ``None`` accepts both (missing -> no score
    column, or score 1.0 for lines that lack it when other lines have it is refused).
    """
    path = Path(path)
    rows = [_parse_label_line(path, no, line, with_score)
            for no, line in enumerate(_read_text(path).splitlines(), start=1) if line.strip()]
    if not rows:
        return Labels.empty(with_score=bool(with_score))
    lengths = {len(r[1]) for r in rows}
    if len(lengths) > 1:
        raise KittiError(path, "some lines have a score and some do not")
    a = np.array([r[1] for r in rows], dtype=np.float64)
    return Labels(name=np.array([r[0] for r in rows], dtype=object), truncated=a[:, 0],
                  occluded=a[:, 1].astype(int), alpha=a[:, 2], bbox=a[:, 3:7], dimensions=a[:, 7:10],
                  location=a[:, 10:13], rotation_y=a[:, 13], score=a[:, 14] if a.shape[1] == 15 else None)


def format_labels(labels: Labels) -> str:
    lines = []
    for i in range(len(labels)):
        vals = [labels.truncated[i], labels.occluded[i], labels.alpha[i], *labels.bbox[i],
                *labels.dimensions[i], *labels.location[i], labels.rotation_y[i]]
        text = f"{labels.name[i]} {vals[0]:.2f} {int(vals[1])} " + " ".join(f"{v:.4f}" for v in vals[2:])
        if labels.score is not None:
            text += f" {labels.score[i]:.6f}"
        lines.append(text)
    return "".join(line + "\n" for line in lines)


def write_labels(path, labels: Labels) -> Path:
    return atomic_write_text(path, format_labels(labels))


# ----------------------------------------------------------------------------- images
@contextmanager
def _opened_image(path: Path):
    """The image at ``path`` opened with PIL, its errors as KittiErrors naming it."""
    try:
        with Image.open(path) as im:
            yield im
    except FileNotFoundError:
        raise KittiError(path, "file not found") from None
    except (OSError, SyntaxError) as e:
        raise KittiError(path, f"not a readable image ({e})") from None


def read_image(path) -> np.ndarray:
    """(H, W, 3) uint8 RGB."""
    path = Path(path)
    with _opened_image(path) as im:
        if im.mode not in ("RGB", "RGBA", "L", "P", "LA", "CMYK", "YCbCr"):  # 16-bit / float: clipped to white
            raise KittiError(path, f"a {im.mode} image; expected 8 bits per channel (RGB or grey)")
        return np.asarray(im.convert("RGB"))


def image_size(path) -> tuple[int, int]:
    """(H, W) of an image file, read from its header."""
    with _opened_image(Path(path)) as im:
        return im.height, im.width


def check_image_fits_calib(path, hw: tuple[int, int], calib: "Calib", calib_path) -> None:
    """Refuse an image that cannot be the one ``calib``'s P2 describes: its principal point must
    lie inside the picture (KITTI: (609.6, 172.9) in 1242 x 375)."""
    m = calib.P2[:, :3]
    u, v, s = m @ m[2]  # the principal point: the image of the optical axis (Hartley & Zisserman 6.2.2)
    cx, cy = u / s, v / s
    h, w = hw
    if not (0 <= cx <= w and 0 <= cy <= h):
        raise KittiError(path, f"the image is {w} x {h} pixels, but {calib_path}'s P2 puts the principal point at "
                               f"({cx:.1f}, {cy:.1f}), outside it: the image and the calibration do not belong together")


def write_image(path, rgb: np.ndarray) -> Path:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: image must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, format="PNG", compress_level=6)
    return atomic_write_bytes(path, buf.getvalue())


# ----------------------------------------------------------------------------- ImageSets, meta
def read_image_set(path) -> list[str]:
    path = Path(path)
    ids, line_of = [], {}
    for no, line in enumerate(_read_text(path).splitlines(), start=1):
        fid = line.strip()
        if not fid:
            continue
        if not fid.isdigit():
            raise KittiError(path, f"frame id {fid!r} is not a number", no)
        if fid in line_of:
            raise KittiError(path, f"frame id {fid} is listed twice (lines {line_of[fid]} and {no})", no)
        line_of[fid] = no
        ids.append(fid)
    return ids


def write_image_set(path, ids) -> Path:
    return atomic_write_text(path, "".join(f"{i}\n" for i in ids))


def read_frames_meta(path) -> pd.DataFrame:
    path = Path(path)
    try:
        df = pd.read_csv(path, dtype={"frame_id": str})
    except FileNotFoundError:
        raise KittiError(path, "file not found") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as e:
        raise KittiError(path, f"not a readable CSV table ({e})") from None
    if "frame_id" not in df.columns:
        raise KittiError(path, "no frame_id column")
    df["frame_id"] = df["frame_id"].str.zfill(6)
    twice = df["frame_id"][df["frame_id"].duplicated()]
    if len(twice):
        rows = (np.flatnonzero(df["frame_id"] == twice.iloc[0]) + 2).tolist()  # + header, 1-based
        raise KittiError(path, f"frame_id {twice.iloc[0]} appears more than once (lines {', '.join(map(str, rows))})")
    return df


def write_frames_meta(path, df: pd.DataFrame) -> Path:
    return atomic_write_text(path, df.to_csv(index=False, lineterminator="\n"))
