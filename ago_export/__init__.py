"""ago_export: checkpoint -> ONNX bundle, parity-checked (torch + onnx).

May import: ago_runtime and ago_train (the model definition and checkpoint format it exports);
nothing imports ago_export but its verb module's entry in ago_runtime.cli's table.
"""
