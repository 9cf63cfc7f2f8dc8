"""The slab loop's time against the slab size, per path of the voxel decision (the runtime's SLAB_BYTES rule).

    python -m benchmarks.slab_size [--bundle DIR] [--frames 4] [--rounds 4] [--work work/slab_size] \
        [--out benchmarks/results/slab_size.md]

One process, one Predictor on the bundle (default: the shipped one), every core. A synthetic town of --frames
keyframes (`ago synth --scenes 1 --frames N --image-size 704x396 --grid 100x100x8 --seed 11`, made once in --work),
each frame preprocessed and its TPV planes computed once; timed is the slab loop alone
(`VoxelClassifier.classify` given the planes: first activation, voxel stages, bank products, decision), per
path: the training bank with the identifier "none" (the default for a closed-world bank), with "min-entropy"
(the adapted branch on the occupied voxels), and with volumes (both branches on every voxel, `ago infer
--save-volumes`). Per round the slab sizes run one after the other, their order reversed every other round;
"auto" is the runtime's own choice (no slab_voxels: encoder.SplitEncoder.slab_rows from SLAB_BYTES). Labels of
every size are checked against the auto run's. Records the CPU model and its flags and the load average.
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SIZES = ("auto", 3200, 6400, 12800, 25600, 51200)       # voxels per slab (whole x rows: rounded down to rows)
PATHS = (("none", "none", False), ("min-entropy", "min-entropy", False), ("volumes", "min-entropy", True))


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=None, help="bundle folder (default: the shipped default bundle)")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--work", type=Path, default=Path("work/slab_size"))
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "slab_size.md")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.rounds < 1:
        sys.exit("error: --frames, --rounds: must be at least 1")

    from ago_runtime.atomic import write_text
    from ago_runtime.predict.bundle import resolve_bundle
    from ago_runtime.predict.encoder import SLAB_BYTES
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.predictor import Predictor
    from benchmarks.bf16_openvino import make_town
    from benchmarks.machine import cpu_model_and_flags, speed_flags
    from benchmarks.infer_speed import git_commit

    load_before = uptime()
    t0 = time.perf_counter()
    p = Predictor(resolve_bundle(args.bundle))
    enc = p.encoder
    X, Y, Z = enc.grid.shape
    town = make_town(args.work, args.frames)
    frames = [p.prepare(f.images, f.rig, f.source) for f in open_frames(town)][: args.frames]
    planes = [enc.plane_maps(x, m) for x, m in frames]
    bank = p.bundle.load_bank()
    rows_auto = {}
    table = []
    for path, identifier, volumes in PATHS:
        folded = p.fold_with_reference(bank) if volumes else p.fold(bank)
        rows_auto[path] = enc.slab_rows(folded.num_rows, volumes)
        times = {s: [] for s in SIZES}
        labels = {}
        for r in range(args.rounds):
            for size in SIZES if r % 2 == 0 else SIZES[::-1]:
                enc.slab_voxels = None if size == "auto" else size
                for i, ((x, m), pl) in enumerate(zip(frames, planes)):
                    t = time.perf_counter()
                    out, _ = p.classifier.classify(x, m, folded, identifier, volumes, pl)
                    times[size].append(time.perf_counter() - t)
                    labels[(size, i)] = out["label"]
        enc.slab_voxels = None
        best = min(statistics.median(v) for v in times.values())
        for size in SIZES:
            rows = rows_auto[path] if size == "auto" else enc.rows_per_slab(size)
            same = np.mean([np.mean(labels[(size, i)] == labels[("auto", i)]) for i in range(len(frames))])
            med = statistics.median(times[size])
            table.append(f"| {path} | {size} | {rows} | {rows * Y * Z} | {1000 * med:.1f} | {1000 * min(times[size]):.1f} "
                         f"| {med / best:.2f} | {100 * same:.3f} |")
    load_after = uptime()
    model, flags = cpu_model_and_flags()
    keep = speed_flags(flags)
    cmd = "python -m benchmarks.slab_size " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    c = p.bundle.contract
    lines = [
        "# The slab loop against the slab size, per path of the voxel decision",
        "",
        f"Command: `{cmd.strip()}` (commit {git_commit(REPO)}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
        "",
        f"CPU: {model}, flags of interest: {' '.join(keep) or 'none'}.  ",
        f"Bundle: `{args.bundle or 'the shipped default bundle'}`, grid {X}x{Y}x{Z} ({Y * Z} voxels an x row), "
        f"h width {c.hidden_dim}, g width {c.adapted_dim}; the widest per-voxel array {enc.widest[0]} (h, main "
        f"stages), {enc.widest[1]} with the adapted branch on every voxel; SLAB_BYTES {SLAB_BYTES >> 20} MiB.  ",
        f"Frames: {len(frames)} keyframes of a synthetic town (seed 11), {args.rounds} rounds; the training bank "
        f"({bank.num_classes} classes); timed: the slab loop given the frame's planes, every core.  ",
        f"Load: before `{load_before}`; after `{load_after}`.",
        "",
        "| path | slab voxels asked | x rows a slab | voxels a slab | slab loop (ms, median) | min (ms) "
        "| vs fastest | labels = auto (%) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
        *table,
        "",
        f"Total time of this run: {time.perf_counter() - t0:.0f} s.",
        "",
    ]
    write_text(args.out, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
