"""Predict many frames with one bundle: reading, prediction and writing overlap (`FramePipeline`).

    from ago_runtime.predict.bundle import Bundle
    from ago_runtime.predict.pipeline import FramePipeline, PipelineFrame

    bundle = Bundle.load("my_bundle")
    pipe = FramePipeline(bundle, bundle.load_bank())            # or load_prompt_bank("ow", bundle=bundle)
    frames = (PipelineFrame(name, images, rig) for name, images, rig in my_frames)
    kept = pipe.run(frames, write=lambda name, images, pred: [pred.semantics])

Three stages run at once in threads (numpy, OpenCV and onnxruntime release the GIL): a reader takes the
next frames from `frames` and preprocesses them, `workers` threads predict (one Predictor, its sessions
with cpu_count // workers threads each), and a writer hands each Prediction to `write` in frame order.
The first frame is read and checked before anything is written, while the Predictor's sessions open in
another thread. An error in any stage ends the run with that error; the frames already handed to
`write` stay written (`ago infer` writes each file atomically).

Only the Predictor's per-frame API is used: `prepare_inputs` (the bundle's preprocessing, no sessions),
`Predictor(...)` and `Predictor.predict_arrays`. Which frames to skip (`ago infer`'s resume) is the
frame source's choice: `frames` holds only the frames to predict.
"""

from __future__ import annotations

import collections
import os
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Iterable, NamedTuple

import numpy as np

from ago_runtime.geometry.camera import Rig
from ago_runtime.predict.bundle import Bundle
from ago_runtime.predict.predictor import Prediction, Predictor, prepare_inputs
from ago_runtime.progress import track
from ago_runtime.vocab.bank import PromptBank


class PipelineFrame(NamedTuple):
    """One frame to predict: its name (the output's name), images (camera -> RGB uint8), rig, and what to
    name in errors (a folder or data file)."""

    name: str
    images: dict[str, np.ndarray]
    rig: Rig
    source: Any = None


# write(name, images, prediction) -> a list of results (e.g. the files written), gathered in frame order
Write = Callable[[str, dict, Prediction], list]


def auto_workers(frames: int) -> int:
    """Frames predicted at once: 2 over several frames on a multi-core CPU (each with half the cores'
    onnxruntime threads; benchmarks/infer_ab.py compares the choices), 1 for a single frame (which then
    gets every core)."""
    return 2 if frames > 1 and (os.cpu_count() or 1) >= 2 else 1


@dataclass
class FramePipeline:
    """Predicts a stream of frames with `bundle` and `bank` (see the module docstring).

    identifier: None = the bundle's choice for this bank (`Bundle.identifier_for`).
    volumes: also the unexplained-obstacle volumes (`Predictor.predict_arrays(volumes=True)`).
    workers: frames predicted at once (None = `auto_workers` of the run's frame count, else 1).
    int8, warm_up: passed to the Predictor the pipeline opens; warm_up is off by default here (a dummy
    frame costs about as much as the first real frame saves).
    progress: the progress bar's label (stderr), None for no bar."""

    bundle: Bundle
    bank: PromptBank
    identifier: str | None = None
    volumes: bool = False
    workers: int | None = None
    int8: bool = False
    warm_up: bool = False
    progress: str | None = "predicting"
    device: str = "cpu"          # the graphs' execution provider (ago_runtime/providers.py)
    precision: str = "fp32"

    def run(self, frames: Iterable[PipelineFrame], write: Write, total: int | None = None,
            predictor: Predictor | None = None) -> list:
        """Predict every frame of `frames` and hand each to `write` in order; gives what `write` returned,
        concatenated. `total`: the number of frames when `frames` has no len() (the progress bar, the
        workers' choice). `predictor`: an open Predictor of this bundle to use; None opens one."""
        count = total if total is not None else (len(frames) if hasattr(frames, "__len__") else None)
        frames = iter(frames)
        workers = self.workers or auto_workers(count if count is not None else 2)   # unknown: several
        identifier = self.identifier or self.bundle.identifier_for(self.bank)
        opened: dict = {}

        def open_predictor():
            try:
                opened["predictor"] = predictor or Predictor(
                    self.bundle, int8=self.int8, warm_up=self.warm_up, device=self.device, precision=self.precision,
                    threads=max(1, (os.cpu_count() or 1) // workers) if workers > 1 else None)
                p = opened["predictor"]   # the bank folded once per run (volumes: with the reference classes)
                opened["folded"] = p.fold_with_reference(self.bank) if self.volumes else p.fold(self.bank)
            except BaseException as e:   # re-raised by the calling thread
                opened["error"] = e

        def read(frame: PipelineFrame):
            t = time.perf_counter()
            x, m = prepare_inputs(self.bundle, frame.images, frame.rig, frame.source)
            return frame.name, frame.images, x, m, time.perf_counter() - t

        opener = threading.Thread(target=open_predictor, daemon=True)
        opener.start()
        try:
            first = next(frames, None)
            first = read(first) if first is not None else None   # checked before anything is written
        finally:
            opener.join()
        if "error" in opened:
            raise opened["error"]
        if first is None:
            return []
        p, folded = opened["predictor"], opened["folded"]

        def predict(item):
            name, images, x, m, t_pre = item
            pred = p.predict_arrays(x, m, self.bank, identifier, folded, volumes=self.volumes)
            pred.timings = {"preprocess": t_pre, **pred.timings}
            return name, images, pred

        return _overlapped(first, frames, read, predict, write, workers, self.progress, count)


def _overlapped(first, frames, read, predict, write: Write, workers: int, progress: str | None,
                count: int | None) -> list:
    """The three stages: a reader thread (read), `workers` predicting threads (predict, in the calling
    thread when 1), a writer thread (write, in frame order)."""
    prepared: queue.Queue = queue.Queue(maxsize=workers + 1)
    to_write: queue.Queue = queue.Queue(maxsize=workers + 1)
    stop = threading.Event()
    written: list = []
    reader = threading.Thread(target=_read_ahead, args=(frames, read, prepared, stop), daemon=True)
    writer = _Writer(lambda item: written.extend(write(*item)), to_write)
    reader.start()
    writer.start()

    def stream():
        yield first
        while (item := prepared.get()) is not None:
            if isinstance(item, BaseException):
                raise item
            yield item

    items = track(stream(), progress, total=count) if progress else stream()
    pool = ThreadPoolExecutor(workers, thread_name_prefix="ago-predict") if workers > 1 else None
    in_flight: collections.deque = collections.deque()   # futures in frame order
    try:
        for item in items:
            if writer.error is not None:
                break
            if pool is None:
                to_write.put(predict(item))
                continue
            in_flight.append(pool.submit(predict, item))
            if len(in_flight) >= workers:
                to_write.put(in_flight.popleft().result())
        while in_flight and writer.error is None:      # the last frames; their errors propagate
            to_write.put(in_flight.popleft().result())
    finally:
        if pool is not None:   # on an error: the frames already submitted are finished and written, in order
            while in_flight and writer.error is None:
                try:
                    to_write.put(in_flight.popleft().result())
                except BaseException:
                    break
            for fut in in_flight:
                fut.cancel()
            pool.shutdown(wait=True)
        stop.set()
        while reader.is_alive():           # unblock a reader waiting on a full queue
            try:
                prepared.get(timeout=0.05)
            except queue.Empty:
                pass
        to_write.put(None)
        writer.join()
    if writer.error is not None:
        raise writer.error
    return written


def _read_ahead(frames, read, outbox: queue.Queue, stop: threading.Event) -> None:
    """Reader thread: read(frame) for each frame onto `outbox`, then None; an exception is put on the
    queue instead (the consumer re-raises it). Stops early when `stop` is set."""
    try:
        for frame in frames:
            if stop.is_set():
                return
            outbox.put(read(frame))
        outbox.put(None)
    except BaseException as e:  # handed to the main thread
        outbox.put(e)


class _Writer(threading.Thread):
    """Writer thread: write(item) for each item of `inbox` until None. The first exception is kept in
    `error` (the main thread re-raises it) and later items are dropped, so the queue never blocks."""

    def __init__(self, write, inbox: queue.Queue):
        super().__init__(daemon=True)
        self.write, self.inbox = write, inbox
        self.error: BaseException | None = None

    def run(self) -> None:
        while (item := self.inbox.get()) is not None:
            if self.error is None:
                try:
                    self.write(item)
                except BaseException as e:
                    self.error = e
