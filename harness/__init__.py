"""sotif-bench harness: KITTI I/O, boxes, evaluation, inference, reports, CLI."""
