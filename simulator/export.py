"""Look at a generated frame: PLY export for MeshLab (points + box edges) and a preview figure."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from harness.core import kitti  # noqa: E402
from harness.core.boxes import corners_3d  # noqa: E402
from harness.core.files import atomic_write_text  # noqa: E402

BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]])
CLASS_COLOURS = {"Car": (0, 200, 0), "Van": (0, 120, 255), "Truck": (255, 140, 0), "DontCare": (150, 150, 150)}


def ply_text(points: np.ndarray, boxes: np.ndarray, names) -> str:
    """ASCII PLY: points coloured by intensity, box corners as vertices joined by edges."""
    corners = corners_3d(boxes).reshape(-1, 3) if len(boxes) else np.zeros((0, 3))
    grey = (np.clip(points[:, 3], 0, 1) * 205 + 50).astype(int)
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points) + len(corners)}", "property float x",
             "property float y", "property float z", "property uchar red", "property uchar green",
             "property uchar blue", f"element edge {12 * len(boxes)}", "property int vertex1", "property int vertex2",
             "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    lines += [f"{x:.3f} {y:.3f} {z:.3f} {g} {g} {g}" for (x, y, z, _), g in zip(points, grey)]
    for k, name in enumerate(names):
        r, g, b = CLASS_COLOURS.get(name, (255, 0, 255))
        lines += [f"{x:.3f} {y:.3f} {z:.3f} {r} {g} {b}" for x, y, z in corners[8 * k: 8 * k + 8]]
    base = len(points)
    for k, name in enumerate(names):
        r, g, b = CLASS_COLOURS.get(name, (255, 0, 255))
        lines += [f"{base + 8 * k + i} {base + 8 * k + j} {r} {g} {b}" for i, j in BOX_EDGES]
    return "\n".join(lines) + "\n"


def export_ply(root: Path, frame_id: str, out: Path) -> Path:
    """Write frame `frame_id` of a data set as a PLY file (LiDAR frame, metres)."""
    points = kitti.read_points(kitti.frame_path(root, "velodyne", frame_id))
    labels = kitti.read_labels(kitti.frame_path(root, "label_2", frame_id))
    calib = kitti.read_calib(kitti.frame_path(root, "calib", frame_id))
    return atomic_write_text(out, ply_text(points, labels.to_lidar(calib), list(labels.name)))


def preview(root: Path, frame_id: str, out: Path, title: str = "") -> Path:
    """PNG with the bird's-eye view of the scan (boxes drawn) above the camera image."""
    points = kitti.read_points(kitti.frame_path(root, "velodyne", frame_id))
    labels = kitti.read_labels(kitti.frame_path(root, "label_2", frame_id))
    calib = kitti.read_calib(kitti.frame_path(root, "calib", frame_id))
    image = kitti.read_image(kitti.frame_path(root, "image_2", frame_id))
    fig, (ax_bev, ax_img) = plt.subplots(2, 1, figsize=(12, 10), gridspec_kw={"height_ratios": [2.2, 1]})
    keep = (np.abs(points[:, 1]) < 40) & (points[:, 0] > -20) & (points[:, 0] < 100)
    ax_bev.scatter(points[keep, 0], points[keep, 1], s=0.2, c=points[keep, 3], cmap="viridis", vmin=0, vmax=0.6)
    for box, name in zip(labels.to_lidar(calib), labels.name):
        c = corners_3d(box[None])[0, :4, :2]
        colour = np.array(CLASS_COLOURS.get(name, (255, 0, 255))) / 255
        ax_bev.plot(*np.vstack([c, c[:1]]).T, color=colour, lw=1.2)
    ax_bev.set(xlim=(-20, 100), ylim=(-40, 40), aspect="equal", xlabel="x (m)", ylabel="y (m)",
               title=f"{title} frame {frame_id}: {len(points)} points")
    ax_img.imshow(image)
    for bb, name in zip(labels.bbox, labels.name):
        colour = np.array(CLASS_COLOURS.get(name, (255, 0, 255))) / 255
        ax_img.add_patch(plt.Rectangle(bb[:2], bb[2] - bb[0], bb[3] - bb[1], fill=False, color=colour, lw=1))
    ax_img.axis("off")
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
