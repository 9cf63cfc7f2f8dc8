"""The library API's script in docs/runtime.md (`from ago_runtime import Predictor, open_frames`), run exactly as
the doc shows it, on a two-keyframe cut of the real nuScenes scene in ../shared (skipped when absent) with the
shipped default bundle: one npz per keyframe, named by its sample token, with the labels `ago infer` writes."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ago_runtime.formats.nuscenes_cut import cut_dataroot
from ago_runtime.predict.bundle import resolve_bundle

REPO = Path(__file__).resolve().parents[1]


def doc_script() -> str:
    """The python block of docs/runtime.md that calls predict_many."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "docs" / "runtime.md").read_text(), re.S)
    (script,) = [b for b in blocks if "predict_many(" in b]
    return script


def test_the_documented_script_runs_a_dataroot(tmp_path):
    from conftest import shared_path

    src = shared_path("nuscenes-scene")
    data = tmp_path / "data"
    record = cut_dataroot(src, data, 1, 1)                      # the scene's first two keyframes
    script = tmp_path / "run.py"
    script.write_text(doc_script())
    assert len([ln for ln in script.read_text().splitlines() if ln.strip() and not ln.startswith("#")]) <= 10
    bundle = resolve_bundle(None)
    env = {**os.environ, "PYTHONPATH": str(REPO), "AGO_NO_PROGRESS": "1"}
    r = subprocess.run([sys.executable, str(script), str(bundle), str(data), str(tmp_path / "out")],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    tokens = record["train_tokens"] + record["val_tokens"]
    assert sorted(p.stem for p in (tmp_path / "out").glob("*.npz")) == sorted(tokens)
    # the same labels as `ago infer` (the CLI is a caller of the same predict_many)
    r = subprocess.run([sys.executable, "-m", "ago_runtime.cli", "infer", "--images", str(data), "--bundle",
                        str(bundle), "--out", str(tmp_path / "cli"), "--picture", "none"],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    for token in tokens:
        with np.load(tmp_path / "out" / f"{token}.npz") as a, np.load(tmp_path / "cli" / f"{token}.npz") as b:
            np.testing.assert_array_equal(a["semantics"], b["semantics"])
            np.testing.assert_array_equal(a["class_names"], b["class_names"])
