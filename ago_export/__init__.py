"""ago_export: checkpoint -> ONNX bundle, parity-checked (torch + onnx)."""
