"""Where `ago export`'s peak memory goes (issue 35: 9.3 GB peak RSS with --readout-grid 200x200x16).

    nice -n 10 python benchmarks/export_memory.py CHECKPOINT [--parity-frame DATAROOT] [--readout-grid 200x200x16] \
        [--out benchmarks/results/export_memory.md]

Runs ago_export.export.export_bundle once in this process (into a temporary folder, deleted after) with
its steps wrapped, read-only: each step's name is pushed on a stack while it runs, and a thread reads
this process's resident set size (/proc/self/statm) every 5 ms and keeps, per step, the RSS at its
start and the highest RSS seen while it was the innermost running step. The steps wrapped are the
ONNX export, the parity check and, inside it, the torch forward on the read-out grid, the ONNX
encoder's h / g, the embeddings from them, the float64 reference labels and the runtime's labels.
Nothing in ago_export is changed: the wrappers replace module attributes for the run only.
Writes a markdown table (step, RSS at start, peak while innermost, peak minus start) with the command.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ago_runtime.atomic import write_text  # noqa: E402

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


class StepMemory:
    """RSS per step: start, and the peak while the step is the innermost one running."""

    def __init__(self, period_s: float = 0.005):
        self.stack: list[str] = ["(outside the wrapped steps)"]
        self.rows: dict[str, dict] = {}
        self.order: list[str] = []
        self.period_s = period_s
        self.overall_peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _row(self, name: str) -> dict:
        if name not in self.rows:
            self.rows[name] = {"start_mb": rss_mb(), "peak_mb": 0.0, "calls": 0, "seconds": 0.0}
            self.order.append(name)
        return self.rows[name]

    def _sample(self) -> None:
        while not self._stop.is_set():
            r = rss_mb()
            self.overall_peak = max(self.overall_peak, r)
            row = self.rows.get(self.stack[-1])
            if row is not None:
                row["peak_mb"] = max(row["peak_mb"], r)
            time.sleep(self.period_s)

    def __enter__(self):
        self._row(self.stack[0])
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    @contextlib.contextmanager
    def step(self, name: str):
        row = self._row(name)
        row["calls"] += 1
        self.stack.append(name)
        t = time.perf_counter()
        try:
            yield
        finally:
            row["seconds"] += time.perf_counter() - t
            row["peak_mb"] = max(row["peak_mb"], rss_mb())
            self.stack.pop()

    def wrap(self, owner, attr: str, name: str):
        """Replace owner.attr by a wrapper that runs it as step `name`; returns an undo function."""
        original = getattr(owner, attr)

        def wrapped(*args, **kwargs):
            with self.step(name):
                return original(*args, **kwargs)
        setattr(owner, attr, wrapped)
        return lambda: setattr(owner, attr, original)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--parity-frame", default=str(REPO.parent / "shared/data/nuscenes-scene"))
    ap.add_argument("--readout-grid", default="200x200x16")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/export_memory.md"))
    args = ap.parse_args(argv)

    from ago_export import export, parity
    from ago_runtime.geometry.grid import Grid
    from ago_runtime.predict.encoder import SplitEncoder
    from ago_train.model.ago_model import AGOModel

    mem = StepMemory()
    undo = [
        mem.wrap(export, "load_model", "load checkpoint + build model"),
        mem.wrap(export, "export_onnx", "ONNX export (torch.onnx.export + onnx.checker)"),
        mem.wrap(export, "check_parity", "parity check (all of it)"),
        mem.wrap(AGOModel, "forward", "parity: torch forward on the read-out grid"),
        mem.wrap(SplitEncoder, "hidden", "parity: ONNX encoder h, g (all voxels)"),
        mem.wrap(parity, "embeddings", "parity: F, F~ from h, g (numpy)"),
        mem.wrap(parity, "reference_labels", "parity: float64 reference labels"),
        mem.wrap(parity, "runtime_labels", "parity: runtime labels (slab loop)"),
    ]
    t = time.perf_counter()
    with mem, tempfile.TemporaryDirectory(dir=REPO / "work") as tmp:
        readout = Grid.parse(args.readout_grid, "--readout-grid")   # as `ago export --readout-grid`
        export.export_bundle(args.checkpoint, Path(tmp) / "bundle", parity_frame_dir=args.parity_frame,
                             bank_prompts=[], readout_grid=readout, log=lambda s: None)
    wall = time.perf_counter() - t
    for u in undo:
        u()
    with open("/proc/self/status") as f:
        hwm = next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmHWM"))

    command = "nice -n 10 python benchmarks/export_memory.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    lines = ["# Where `ago export`'s peak memory goes (issue 35)", "",
             f"Command: `{command}` ({time.strftime('%Y-%m-%d')}, a 2-core CPU shared with other work; "
             "the RSS numbers do not depend on the load, the seconds do).", "",
             f"One export_bundle run in-process, read-out grid {args.readout_grid}, parity frame "
             f"`{args.parity_frame}`, no extra banks: {wall:.0f} s, process peak RSS (VmHWM) {hwm:.0f} MB; "
             f"highest sampled RSS {mem.overall_peak:.0f} MB. RSS sampled every 5 ms; \"peak\" is the highest RSS "
             "while the step was the innermost wrapped step running.", "",
             "| step | calls | seconds | RSS at start (MB) | peak while innermost (MB) | peak - start (MB) |",
             "|---|---:|---:|---:|---:|---:|"]
    for name in mem.order:
        r = mem.rows[name]
        lines.append(f"| {name} | {r['calls']} | {r['seconds']:.1f} | {r['start_mb']:.0f} | {r['peak_mb']:.0f} | "
                     f"{r['peak_mb'] - r['start_mb']:.0f} |")
    write_text(Path(args.out), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return {"rows": mem.rows, "hwm_mb": hwm}


if __name__ == "__main__":
    main()
