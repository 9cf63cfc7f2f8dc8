"""ago_runtime.predict: running an exported model - bundle + images + rig + prompt bank -> occupancy.

Holds `contract` (the bundle's schema: bundle.json, heads.npz, the graphs' names), `card` (the bundle card's
schema), `bundle` (Bundle: the exported folder, read and checked), `encoder` (the ONNX camera-to-voxel
encoder, slab by slab), `heads` (the linear heads folded with a bank, numpy), `predictor`
(Predictor, Prediction; `predict_many` for many frames), `frames` (open_frames: the frames of a folder,
dataset or info file), `pipeline` (the overlap of reading, prediction and the caller's work) and `cli`
(`ago infer`, `ago demo`, `ago retrieve`).

May import: numpy, onnxruntime, OpenCV, ago_runtime's basics, geometry, formats and vocab;
`cli` may also import pictures and typer.
"""
