"""Text side of training: the MiniLM sentence encoder in torch (and its ONNX export), noise words."""
