"""FramePipeline from Python (ago_runtime/predict/pipeline.py): many frames through one bundle, in order,
with what Predictor.predict gives per frame; a bad frame ends the run after the frames before it are
written. Uses the shipped default bundle and demo frame (no torch)."""

from __future__ import annotations

import numpy as np
import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime.formats.calibration import load_images_folder
from ago_runtime.predict.bundle import DEMO_FRAME_DIR, Bundle, resolve_bundle
from ago_runtime.predict.pipeline import FramePipeline, PipelineFrame
from ago_runtime.predict.predictor import Predictor


@pytest.fixture(scope="module")
def demo():
    if not DEMO_FRAME_DIR.is_dir():
        pytest.skip("no demo frame installed")
    bundle = Bundle.load(resolve_bundle(None))
    images, rig, _ = load_images_folder(DEMO_FRAME_DIR, fallback_rig=bundle.rig)
    # three different frames: the demo, its images mirrored, its images darkened
    frames = [PipelineFrame("demo", images, rig, DEMO_FRAME_DIR),
              PipelineFrame("mirrored", {k: np.ascontiguousarray(v[:, ::-1]) for k, v in images.items()}, rig),
              PipelineFrame("dark", {k: (v // 3).astype(np.uint8) for k, v in images.items()}, rig)]
    return bundle, frames


def test_pipeline_predicts_every_frame_in_order_as_predict_does(demo):
    bundle, frames = demo
    bank = bundle.load_bank()
    seen = []

    def write(name, images, pred):
        seen.append(name)
        assert pred.timings["preprocess"] >= 0 and "encoder" in pred.timings
        return [(name, pred.semantics.copy())]

    got = FramePipeline(bundle, bank, workers=2, progress=None).run(frames, write)
    assert seen == [f.name for f in frames] and [n for n, _ in got] == seen
    predictor = Predictor(bundle)
    expected = [predictor.predict(f.images, f.rig, bank).semantics for f in frames]
    for (_, sem), exp in zip(got, expected):
        np.testing.assert_array_equal(sem, exp)
    assert not np.array_equal(expected[0], expected[2])   # the frames differ, so the order is checked
    # an open Predictor can be reused, one frame at a time, from a generator of unknown length
    again = FramePipeline(bundle, bank, workers=1, progress=None).run(
        (f for f in frames), lambda name, images, pred: [pred.semantics], predictor=predictor)
    for sem, exp in zip(again, expected):
        np.testing.assert_array_equal(sem, exp)


def test_a_bad_frame_ends_the_run_after_the_frames_before_it(demo):
    bundle, frames = demo
    square = dict(frames[0].images, CAM_FRONT=np.zeros((90, 90, 3), np.uint8))   # not the rig's aspect ratio
    broken = PipelineFrame("square", square, frames[0].rig, "broken/")
    written = []
    pipe = FramePipeline(bundle, bundle.load_bank(), workers=2, progress=None)
    with pytest.raises(AgoInputError):
        pipe.run([frames[0], broken, frames[2]], lambda name, images, pred: written.append(name) or [name])
    assert written == ["demo"]
    with pytest.raises(AgoInputError):   # a bad first frame: nothing is written
        pipe.run([broken, frames[0]], lambda name, images, pred: written.append(name) or [name])
    assert written == ["demo"]
    assert pipe.run([], lambda *a: [1]) == []
