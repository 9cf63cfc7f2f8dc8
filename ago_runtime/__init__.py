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

The library API (docs/runtime.md), importable from here:

    from ago_runtime import Predictor, open_frames
    predictor = Predictor("my_bundle")
    for frame, pred in predictor.predict_many(open_frames("DATAROOT")):
        ...

`Predictor`, `Prediction` (predict/predictor.py), `open_frames`, `InputFrame` (predict/frames.py) and
`load_prompt_bank` (vocab/bank.py) are imported when first read, so that `import ago_runtime.errors`
(and every other submodule) stays free of onnxruntime.
"""

__version__ = "0.1.0"

__all__ = ["Predictor", "Prediction", "open_frames", "InputFrame", "load_prompt_bank"]

# name -> the module that defines it (read by __getattr__ on first use)
_LIBRARY = {"Predictor": "ago_runtime.predict.predictor", "Prediction": "ago_runtime.predict.predictor",
            "open_frames": "ago_runtime.predict.frames", "InputFrame": "ago_runtime.predict.frames",
            "load_prompt_bank": "ago_runtime.vocab.bank"}


def __getattr__(name: str):
    if name in _LIBRARY:
        import importlib

        value = getattr(importlib.import_module(_LIBRARY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
