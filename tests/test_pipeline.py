"""Predictor.predict_many from Python (ago_runtime/predict/predictor.py over predict/pipeline.py): many frames
through one bundle, in order, with what Predictor.predict gives per frame; a bad frame ends the iteration after
the frames before it; leaving the loop early stops the threads. Uses the shipped default bundle and demo frame
(no torch)."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pytest

from ago_runtime import InputFrame, Predictor, open_frames
from ago_runtime.errors import AgoInputError
from ago_runtime.predict.bundle import DEMO_FRAME_DIR, Bundle, resolve_bundle


@pytest.fixture(scope="module")
def demo():
    if not DEMO_FRAME_DIR.is_dir():
        pytest.skip("no demo frame installed")
    bundle = Bundle.load(resolve_bundle(None))
    (frame,) = list(open_frames(DEMO_FRAME_DIR, rig=bundle.rig))
    images, rig = frame.images, frame.rig
    # three different frames: the demo, its images mirrored, its images darkened
    frames = [InputFrame("demo", images, rig, DEMO_FRAME_DIR),
              InputFrame("mirrored", {k: np.ascontiguousarray(v[:, ::-1]) for k, v in images.items()}, rig),
              ("dark", {k: (v // 3).astype(np.uint8) for k, v in images.items()}, rig)]   # a plain tuple too
    return bundle, frames, Predictor(bundle, workers=2)


def test_predict_many_gives_every_frame_in_order_as_predict_does(demo):
    bundle, frames, predictor = demo
    bank = bundle.load_bank()
    got = []
    for frame, pred in predictor.predict_many(frames, bank):
        assert pred.timings["preprocess"] >= 0 and "encoder" in pred.timings
        got.append((frame.name, pred.semantics.copy()))
    assert [n for n, _ in got] == ["demo", "mirrored", "dark"]
    one = Predictor(bundle, workers=1)
    expected = [one.predict(f[1], f[2], bank).semantics for f in frames]
    for (_, sem), exp in zip(got, expected):
        np.testing.assert_array_equal(sem, exp)
    assert not np.array_equal(expected[0], expected[2])   # the frames differ, so the order is checked
    # one worker, from a generator of unknown length
    again = [pred.semantics for _, pred in one.predict_many(f for f in frames)]
    for sem, exp in zip(again, expected):
        np.testing.assert_array_equal(sem, exp)


def test_a_bad_frame_ends_the_run_after_the_frames_before_it(demo):
    bundle, frames, predictor = demo
    square = dict(frames[0].images, CAM_FRONT=np.zeros((90, 90, 3), np.uint8))   # not the rig's aspect ratio
    broken = InputFrame("square", square, frames[0].rig, "broken/")
    seen = []
    with pytest.raises(AgoInputError, match="CAM_FRONT"):
        for frame, _ in predictor.predict_many([frames[0], broken, frames[2]]):
            seen.append(frame.name)
    assert seen == ["demo"]
    with pytest.raises(AgoInputError):   # a bad first frame: nothing is handed out
        for frame, _ in predictor.predict_many([broken, frames[0]]):
            seen.append(frame.name)
    assert seen == ["demo"]
    assert list(predictor.predict_many([])) == []


def test_leaving_the_loop_early_stops_the_threads(demo):
    bundle, frames, predictor = demo
    before = threading.active_count()
    with contextlib.closing(predictor.predict_many(frames * 3)) as predictions:
        for frame, _ in predictions:
            break
    assert frame.name == "demo"
    assert threading.active_count() <= before


def test_a_free_worker_takes_the_next_frame_while_the_caller_is_busy():
    """overlapped: while the caller handles frame 0 (here a 0.4 s sleep; in `ago infer`, its picture and files),
    the workers go on with frames 1..3 instead of idling until the caller asks for the next result."""
    from ago_runtime.predict.pipeline import overlapped

    started: dict[int, float] = {}
    clock = threading.Lock()

    def predict(i: int) -> int:
        with clock:
            started[i] = time.perf_counter()
        time.sleep(0.02)
        return i

    handed = []
    with contextlib.closing(overlapped(range(8), lambda i: i, predict, workers=2)) as results:
        for i in results:
            handed.append(i)
            if i == 0:
                time.sleep(0.4)
                busy_until = time.perf_counter()
    assert handed == list(range(8))
    # frames 1, 2 and 3 were taken up by the workers during the caller's 0.4 s with frame 0
    assert all(started[i] < busy_until - 0.2 for i in (1, 2, 3)), started
