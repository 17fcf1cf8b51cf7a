"""Runtime figures of one detector: torch eager vs onnxruntime latency and agreement, peak memory.

The peak memory is the high-water mark of resident memory (VmHWM) of a fresh process that loads
onnxruntime and runs the ONNX file on a few frames: ``python -m harness.runtime ONNX DATA N``.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from harness.core.kitti import read_image_set
from harness.infer import OnnxDetector, frame_inputs, latency_summary, runtime_reason


def first_test_frames(data: Path, n: int) -> list[str]:
    """The first ``n`` frame ids of the data set's test split (the frames the runtime probes time)."""
    return read_image_set(data / "ImageSets" / "test.txt")[:n]


BOX_ATOL = 1e-4
"""Two runtimes return "the same boxes" when every box value (metres, radians) agrees within this."""


def outputs_agree(a: dict, b: dict, atol: float = BOX_ATOL) -> tuple[bool, float, float]:
    """Same boxes (count, and every value within ``atol`` after sorting by score), the largest
    score difference and the largest box-value difference (nan when the counts differ)."""
    if a["boxes"].shape != b["boxes"].shape:
        return False, float("nan"), float("nan")
    if len(a["scores"]) == 0:
        return True, 0.0, 0.0
    ia, ib = np.argsort(-a["scores"], kind="stable"), np.argsort(-b["scores"], kind="stable")
    box_diff = float(np.abs(a["boxes"][ia].astype(np.float64) - b["boxes"][ib]).max())
    return box_diff <= atol, float(np.abs(a["scores"][ia] - b["scores"][ib]).max()), box_diff


def _timed(fn) -> tuple:
    """``fn()`` once to warm up, then once timed: (its output, milliseconds)."""
    fn()
    t0 = time.perf_counter()
    out = fn()
    return out, 1000 * (time.perf_counter() - t0)


def _agreement(results: list[tuple[bool, float, float]]) -> dict:
    """Share of frames with the same boxes, the largest score and box differences over the frames
    whose box counts match, from ``outputs_agree``."""
    def largest(k):
        vals = [r[k] for r in results if not np.isnan(r[k])]
        return max(vals) if vals else None
    return {"same_boxes": float(np.mean([r[0] for r in results])), "max_abs_score_diff": largest(1),
            "max_abs_box_diff": largest(2), "box_atol": BOX_ATOL, "frames": len(results)}


def compare_torch_onnx(checkpoint: Path, onnx_path: Path, data: Path, n_frames: int = 20) -> dict:
    """torch eager vs onnxruntime on the same frames: p50 latencies, speed ratio, agreement, and the
    onnxruntime latency summary (p50/p90/frames per second) of those frames."""
    import torch
    from models.zoo import load_checkpoint
    model, _ = load_checkpoint(checkpoint)
    model.eval()
    det = OnnxDetector(onnx_path)
    t_torch, t_ort, agree = [], [], []
    fids = first_test_frames(data, n_frames)
    for fid in fids:
        points, _, image, l2i, _ = frame_inputs(det, data, fid)
        args = [torch.from_numpy(points)]
        if det.info.uses_camera:
            args += [torch.from_numpy(image), torch.from_numpy(l2i)]
        with torch.no_grad():
            out_t, ms = _timed(lambda: model(*args))
        t_torch.append(ms)
        out_o, ms = _timed(lambda: det(points, image, l2i))
        t_ort.append(ms)
        agree.append(outputs_agree({"boxes": out_t[0].numpy(), "scores": out_t[1].numpy()}, out_o))
    p50_t, p50_o = float(np.median(t_torch)), float(np.median(t_ort))
    return {"onnxruntime": latency_summary(t_ort), "torch_eager_ms_p50": p50_t, "ort_ms_p50_same_frames": p50_o,
            "ort_speedup": p50_t / p50_o, "agreement": _agreement(agree),
            # per-frame figures, so that every summary above can be recomputed from the run's files
            "frames_ms": {"frame_ids": fids, "onnxruntime": t_ort,
                          "torch_eager": t_torch},
            "peak_memory_mb": peak_memory_mb(onnx_path, data, min(n_frames, 5))}


def _reason(exc: Exception) -> str:
    """The runtime's own error (not the detector's wrapper of it), as ``Type: message``."""
    cause = exc.__cause__ or exc
    return f"{type(cause).__name__}: {runtime_reason(cause)}"


def compare_openvino(onnx_path: Path, data: Path, n_frames: int = 20) -> dict:
    """OpenVINO vs onnxruntime on the same frames: latency p50/p90 and agreement.

    A file that OpenVINO cannot read or run is reported under ``error`` (a finding, not a crash);
    without the optional extra the result is ``{"error": "not installed"}``."""
    try:
        import openvino  # noqa: F401
    except ImportError:
        return {"error": "not installed"}
    ort_det = OnnxDetector(onnx_path)
    try:
        ov_det = OnnxDetector(onnx_path, runtime="openvino")
    except Exception as exc:  # noqa: BLE001 - any compile failure is the finding
        return {"error": f"compile: {_reason(exc)}"}
    t_ov, t_ort, agree = [], [], []
    for fid in first_test_frames(data, n_frames):
        points, _, image, l2i, _ = frame_inputs(ort_det, data, fid)
        try:  # the warm-up call also compiles for this input shape
            out_v, ms = _timed(lambda: ov_det(points, image, l2i))
        except Exception as exc:  # noqa: BLE001
            return {"error": f"frame {fid}: {_reason(exc)}"}
        t_ov.append(ms)
        out_o, ms = _timed(lambda: ort_det(points, image, l2i))
        t_ort.append(ms)
        agree.append(outputs_agree(out_o, out_v))
    if not agree:
        return {"error": "no frames"}
    return {"latency_ms_p50": float(np.median(t_ov)), "latency_ms_p90": float(np.percentile(t_ov, 90)),
            "ort_ms_p50_same_frames": float(np.median(t_ort)), "agreement": _agreement(agree),
            "frames_ms": {"openvino": t_ov, "onnxruntime": t_ort}, "error": None}


def peak_memory_mb(onnx_path: Path, data: Path, n_frames: int = 5) -> float | None:
    proc = subprocess.run([sys.executable, "-m", "harness.runtime", str(onnx_path), str(data), str(n_frames)],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])["peak_memory_mb"]


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _main(argv) -> None:
    onnx_path, data, n = Path(argv[0]), Path(argv[1]), int(argv[2])
    det = OnnxDetector(onnx_path)
    for fid in first_test_frames(data, n):
        points, _, image, l2i, _ = frame_inputs(det, data, fid)
        det(points, image, l2i)
    print(json.dumps({"peak_memory_mb": _vm_hwm_mb()}))


if __name__ == "__main__":
    _main(sys.argv[1:])
