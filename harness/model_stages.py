"""The stages that give a model of a run its checkpoint and ONNX file, trained or imported alike.

- ``checkpoint_of(run_dir, tag)``: where a run keeps the checkpoint of a model's draw (``run.draw_tag``);
- ``export_stage(stages, run_dir, tag, expected_model)``: stage ``export_<tag>``, keyed on the checkpoint and
  on the code of models/ (``models.graph_cache.graph_code``: a changed network exports again);
- ``import_export(stages, cfg, run_dir, tag)``: an imported model's (``harness.published_run``) stage
  ``import_<tag>``, which copies its checkpoint to where a trained model keeps its own, then its export.
"""
from __future__ import annotations

from pathlib import Path

from harness import published_run
from harness.core.files import atomic_write_bytes
from harness.stages import Stages, file_digest
from models.graph_cache import graph_code


def checkpoint_of(run_dir: Path, tag: str) -> Path:
    """Where a run keeps the checkpoint of a model's training draw (``draw_tag``)."""
    return run_dir / "models" / tag / "checkpoint.pt"


def export_stage(stages: Stages, run_dir: Path, tag: str, expected_model: str) -> None:
    """Export the checkpoint of ``tag`` to ``models/<tag>.onnx`` (stage ``export_<tag>``)."""
    from models.export import export_checkpoint
    ckpt, onnx_path = checkpoint_of(run_dir, tag), run_dir / "models" / f"{tag}.onnx"
    say = (lambda msg: print(stages.prefix + msg, flush=True)) if stages.progress else None
    stages.run(f"export_{tag}", {"checkpoint": file_digest(ckpt), "graph_code": graph_code()},
               lambda: {"onnx": str(export_checkpoint(ckpt, onnx_path, expected_model=expected_model, say=say))},
               outputs=[onnx_path])


def import_export(stages: Stages, cfg, run_dir: Path, tag: str) -> dict:
    """Copy an imported model's checkpoint into the run (stage ``import_<tag>``) and export it: the
    trained models' ``run._train_export`` for it. Returns its training record: none."""
    src, ckpt = published_run.source(cfg, tag), checkpoint_of(run_dir, tag)

    def copy() -> dict:
        atomic_write_bytes(ckpt, src.read_bytes())
        return {"from": str(src)}
    stages.run(f"import_{tag}", {"checkpoint": file_digest(src)}, copy, outputs=[ckpt])
    export_stage(stages, run_dir, tag, expected_model=tag.rsplit("_", 1)[0])
    return {}
