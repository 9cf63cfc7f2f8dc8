"""ago_runtime: the light core of ago (numpy + onnxruntime + opencv + typer, never torch).

Everything that needs no torch lives here and is imported by ago_train and ago_export, grouped by
concern (docs/architecture.md):

- basics (modules at this level): errors, atomic (writes), readers, outputs (output-path checks),
  progress, classes (the Occ3D class table);
- geometry/ (grid, cameras, preprocessing), formats/ (Occ3D, Frame, images + calibration, nuScenes,
  mmdet3d), vocab/ (prompt files, text encoder, prompt banks), predict/ (bundle, encoder, heads,
  Predictor), pictures/ (render, charts, overlays), scoring/ (Occ3D metric, ranking);
- cli.py: the `ago` app, its verb table and its one error path; each part's verbs in its cli.py.

May import: numpy, onnxruntime, OpenCV, typer; never ago_train or ago_export (the CLI names their
verb modules as data and loads the ones a command runs).
"""

__version__ = "0.1.0"
