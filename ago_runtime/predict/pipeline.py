"""Reading, prediction and the caller's own work overlap: `overlapped`, the engine of
`Predictor.predict_many` (ago_runtime/predict/predictor.py).

    for result in overlapped(frames, read, predict, workers=2):
        ...   # the caller's loop body (`ago infer` writes the files) runs while the next frames are read and predicted

Two stages run in threads beside the caller (numpy, OpenCV and onnxruntime release the GIL): a reader
thread takes the next items from `frames` and applies `read` (decode, preprocess), `workers` threads apply
`predict`, and the generator hands the results out in frame order. Up to 2 x `workers` frames are handed
to the workers before the oldest is handed out, so that a worker that finishes while the caller handles a
result (`ago infer` draws and writes it) takes the next frame at once instead of waiting for the caller.
An error in reading or predicting ends the iteration with that error once the frames before it have been
handed out; leaving the loop early (break, an error in the loop body) stops the threads when the generator is
closed (`contextlib.closing`, or when it is collected).
"""

from __future__ import annotations

import collections
import os
import queue
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

from ago_runtime.progress import track

__all__ = ["auto_workers", "overlapped"]

F = TypeVar("F")
R = TypeVar("R")


def auto_workers(frames: int) -> int:
    """Frames predicted at once: 2 over several frames on a multi-core CPU (each with half the cores'
    onnxruntime threads; benchmarks/infer_ab.py compares the choices), 1 for a single frame (which then
    gets every core)."""
    return 2 if frames > 1 and (os.cpu_count() or 1) >= 2 else 1


def overlapped(frames: Iterable[F], read: Callable[[F], object], predict: Callable[[object], R], workers: int = 1,
               progress: str | None = None, total: int | None = None) -> Iterator[R]:
    """predict(read(frame)) for each frame, in order, with reading and prediction running ahead of the
    caller (see the module docstring). `progress`: a progress bar's label (stderr), None for none;
    `total`: the frame count for the bar."""
    prepared: queue.Queue = queue.Queue(maxsize=workers + 1)
    stop = threading.Event()
    reader = threading.Thread(target=_read_ahead, args=(iter(frames), read, prepared, stop), daemon=True)
    reader.start()

    def stream():
        while (item := prepared.get()) is not None:
            if isinstance(item, BaseException):
                raise item
            yield item

    items = track(stream(), progress, total=total) if progress else stream()
    pool = ThreadPoolExecutor(workers, thread_name_prefix="ago-predict")
    in_flight: collections.deque = collections.deque()   # futures in frame order
    try:
        while True:
            try:
                item = next(items)
            except StopIteration:
                break
            except Exception:   # a frame that cannot be read: the frames before it are handed out first
                while in_flight:
                    yield in_flight.popleft().result()
                raise
            in_flight.append(pool.submit(predict, item))
            if len(in_flight) >= 2 * workers:
                yield in_flight.popleft().result()
        while in_flight:
            yield in_flight.popleft().result()
    finally:
        for fut in in_flight:
            fut.cancel()
        pool.shutdown(wait=True)
        stop.set()
        while reader.is_alive():           # unblock a reader waiting on a full queue
            try:
                prepared.get(timeout=0.05)
            except queue.Empty:
                pass
        items.close()


def _read_ahead(frames, read, outbox: queue.Queue, stop: threading.Event) -> None:
    """Reader thread: read(frame) for each frame onto `outbox`, then None; an exception is put on the
    queue instead (the consumer re-raises it). Stops early when `stop` is set."""
    try:
        for frame in frames:
            if stop.is_set():
                return
            outbox.put(read(frame))
        outbox.put(None)
    except BaseException as e:  # handed to the consuming thread
        outbox.put(e)
