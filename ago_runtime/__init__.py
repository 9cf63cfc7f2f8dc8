"""ago_runtime: the light core of ago (numpy + onnxruntime + opencv, never torch).

Everything that needs no torch lives here and is imported by ago_train and ago_export:
the Occ3D class table and file format, grid and camera geometry, the nuScenes reader,
prompt files and banks, the Occ3D metric, pictures, and the ONNX predictor.
"""

__version__ = "0.1.0"
