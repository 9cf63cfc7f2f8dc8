"""The bank product in int8 (uint8 features x int8 bank, onnxruntime's MatMulInteger) against fp32: labels and time.

    python -m benchmarks.int8_bank_product [--bundle DIR] [--frames 4] [--work work/int8_bank_product] \
        [--out benchmarks/results/int8_bank_product.md]

Issue 52 item 2 asks for the voxel stages in int8 "where that pays". On the shipped model the per-voxel work
left in fp32 is the first activation and the main branch's bank product, s = A x^T + c (A: the folded bank,
(P+1) x 128; x: every voxel's softplus features, >= 0); with the training bank the identifier is "none" and no
voxel stage runs. This measures what an int8 bank product would give, on the real onnxruntime kernels:

- A per row to int8 (symmetric, scale max|A_p| / 127); x per slab to uint8 (scale max(x) / 255, rounded by
  cv2.convertScaleAbs, one pass); s = MatMulInteger(x_q, A_q^T) (int32) times the two scales, + c;
- the labels of the decision on those scores against the fp32 runtime's labels on every voxel and on the voxels
  either calls occupied, with the fp32 planes graph and, with a bundle that has the int8 variant (`ago export
  --int8`), with the int8 planes graph (the bundle's int8 variant plus an int8 bank product against fp32 throughout);
- the time of the bank product alone per frame, one thread, fp32 (the runtime's BankProduct: one Gemm) against
  the int8 path (quantise + MatMulInteger + rescale + transpose), on the same slabs, alternating.

Frames: a synthetic town (`ago synth --scenes 1 --frames N --image-size 704x396 --grid 100x100x8 --seed 11`,
made once in --work). Records the CPU model and its flags.
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def matmul_integer_session():
    """s (n, P') int32 = MatMulInteger(x (n, d) uint8, bank_t (d, P') int8), one thread."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    node = helper.make_node("MatMulInteger", ["x", "bank_t"], ["s"])
    graph = helper.make_graph([node], "int8_bank_product",
                              [helper.make_tensor_value_info("x", TensorProto.UINT8, ["n", "d"]),
                               helper.make_tensor_value_info("bank_t", TensorProto.INT8, ["d", "p"])],
                              [helper.make_tensor_value_info("s", TensorProto.INT32, ["n", "p"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])


class Int8BankProduct:
    """s = A x^T (P', n) float32 through uint8 x int8 (see the module doc); A quantised once."""

    def __init__(self, A: np.ndarray):
        A = np.asarray(A, np.float32)
        self.scale_a = np.maximum(np.abs(A).max(axis=1), 1e-12) / 127.0
        self.bank_t = np.ascontiguousarray(np.round(A / self.scale_a[:, None]).astype(np.int8).T)
        self.session = matmul_integer_session()

    def __call__(self, x: np.ndarray) -> np.ndarray:
        import cv2

        top = float(x.max())
        alpha = 255.0 / top if top > 0 else 1.0
        q = cv2.convertScaleAbs(x, alpha=alpha)                    # round(|x| * alpha), saturated to 0..255
        (s,) = self.session.run(["s"], {"x": q, "bank_t": self.bank_t})
        s = s.astype(np.float32)
        s *= (self.scale_a / alpha).astype(np.float32)
        return cv2.transpose(s)                                    # (P', n), class-major as the decision reads


def agreement(a: np.ndarray, b: np.ndarray, free: int) -> tuple[int, int, int, int]:
    same = a == b
    either = (a != free) | (b != free)
    return int(same.sum()), int(same.size), int(same[either].sum()), int(either.sum())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default=None, help="bundle folder (default: the shipped one); with an int8 variant "
                                                   "the int8 planes graph is measured too")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=3, help="timing rounds per frame")
    ap.add_argument("--work", type=Path, default=Path("work/int8_bank_product"))
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "int8_bank_product.md")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.rounds < 1:
        sys.exit("error: --frames, --rounds: must be at least 1")

    from ago_runtime.atomic import write_text
    from ago_runtime.predict import decision
    from ago_runtime.predict.bank_product import BankProduct
    from ago_runtime.predict.bundle import resolve_bundle
    from ago_runtime.predict.decision import Branch, Identifier
    from ago_runtime.predict.frames import open_frames
    from ago_runtime.predict.predictor import Predictor
    from benchmarks.bf16_openvino import make_town
    from benchmarks.infer_speed import git_commit
    from benchmarks.machine import cpu_model_and_flags

    t0 = time.perf_counter()
    bundle = resolve_bundle(args.bundle)
    fp32 = Predictor(bundle)
    has_int8 = "int8" in fp32.bundle.contract.variants
    variants = [("fp32", fp32)] + ([("int8", Predictor(bundle, int8=True))] if has_int8 else [])
    bank = fp32.bundle.load_bank()
    identifier = fp32.bundle.identifier_for(bank)
    if Identifier(identifier) is not Identifier.NONE:
        sys.exit(f"error: --bundle: its training bank's identifier is {identifier}, not none: the main branch's bank "
                 "product alone does not decide its labels")
    folded = fp32.fold(bank)
    K, free = folded.num_classes, folded.num_classes
    A, c = folded.A[Branch.MAIN], folded.c[Branch.MAIN]
    int8_product = Int8BankProduct(A)
    fp32_product = BankProduct(1)
    town = make_town(args.work, args.frames)
    frames = [fp32.prepare(f.images, f.rig, f.source) for f in open_frames(town)][: args.frames]

    counts = {}          # (planes variant, bank product) -> agreement sums against fp32 throughout
    times = {"fp32": [], "int8": []}
    for x, m in frames:
        ref = fp32.predict_arrays(x, m, bank, identifier, folded).semantics.reshape(-1)
        for name, pred in variants:
            enc = pred.encoder
            planes = enc.plane_maps(x, m)
            slabs = [enc.first_activation(planes, x0, x1) for x0, x1 in enc.slabs(enc.slab_rows(folded.num_rows))]
            for product in ("fp32", "int8"):
                labels = []
                for h in slabs:
                    s = fp32_product(A, h) if product == "fp32" else int8_product(h)
                    z = decision.class_scores(s, c, folded.layout)
                    f = decision.main_free(z, K)
                    labels.append(decision.decide(z, f, None, np.zeros(0, np.intp), identifier, K, folded.scales).label)
                got = np.concatenate(labels)
                sums = counts.setdefault((name, product), [0, 0, 0, 0])
                for i, v in enumerate(agreement(got, ref, free)):
                    sums[i] += v
            if name == "fp32":
                for r in range(args.rounds):
                    for product in ("fp32", "int8") if r % 2 == 0 else ("int8", "fp32"):
                        t = time.perf_counter()
                        for h in slabs:
                            fp32_product(A, h) if product == "fp32" else int8_product(h)
                        times[product].append(time.perf_counter() - t)
    model, flags = cpu_model_and_flags()
    keep = [f for f in ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8") if f in flags]
    cmd = "python -m benchmarks.int8_bank_product " + " ".join(shlex.quote(a) for a in
                                                               (argv if argv is not None else sys.argv[1:]))
    rows = []
    for (planes, product), (same, n, same_occ, n_occ) in counts.items():
        rows.append(f"| {planes} | {product} | {100 * same / n:.3f} | {100 * same_occ / max(n_occ, 1):.2f} |")
    t32, t8 = statistics.median(times["fp32"]), statistics.median(times["int8"])
    lines = [
        "# The bank product in int8 against fp32: labels and time",
        "",
        f"Command: `{cmd.strip()}` (commit {git_commit(REPO)}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}).",
        "",
        f"CPU: {model}, flags of interest: {' '.join(keep) or 'none'}.  ",
        f"Bundle: `{args.bundle or 'the shipped default bundle'}`{' (with its int8 variant)' if has_int8 else ''}; "
        f"the training bank ({K} classes, {folded.num_rows} score rows), identifier {identifier}; {len(frames)} "
        f"keyframes of a synthetic town (seed 11), {fp32.grid.num_voxels} voxels each.",
        "",
        "## Labels against the fp32 runtime (fp32 planes graph, fp32 bank product)",
        "",
        "| planes graph | bank product | labels = fp32, all voxels (%) | voxels either calls occupied (%) |",
        "|---|---|---:|---:|",
        *rows,
        "",
        "## The bank product alone, one thread, per frame (the same slabs, alternating)",
        "",
        "| bank product | median (ms) | min (ms) | vs fp32 |",
        "|---|---:|---:|---:|",
        f"| fp32 (BankProduct: one Gemm) | {1000 * t32:.1f} | {1000 * min(times['fp32']):.1f} | 1.00x |",
        f"| int8 (convertScaleAbs + MatMulInteger + rescale + transpose) | {1000 * t8:.1f} | "
        f"{1000 * min(times['int8']):.1f} | {t32 / t8:.2f}x |",
        "",
        f"Total time of this run: {time.perf_counter() - t0:.0f} s.",
        "",
    ]
    write_text(args.out, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
