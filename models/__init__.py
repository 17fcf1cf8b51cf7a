"""Seven LiDAR 3D object detectors in plain PyTorch, exportable to ONNX."""
