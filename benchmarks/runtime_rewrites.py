"""What each export / runtime rewrite of bundle format 3 buys, measured A/B in one process.

Every variant is exported from the same random-weight model (the "cpu" preset, 100 x 100 x 8) with
this tree's code and run on the same inputs; variants alternate within each round, and the table
gives the minimum and the median over the rounds (wall and process CPU time: this machine is shared,
the minimum is the least disturbed run). Variants:

planes graph (images -> planes)
- "original TPV": the trained model's own modules (ago_train.model.tpv; per-level grid_samples,
  (B, Q, ...) layouts with short last axes, separate offset / weight linears), batch of 6 images;
- "restructured TPV": ago_export.graphs.PlanesGraph (what `ago export` writes);
- the same with the backbone run on one camera after the other (tried, not shipped).
voxels graph (slab -> scores), one frame of slabs
- "first linear per voxel, log1p softplus": today's per-voxel layout (the TPV features (D, x, Y)
  summed per voxel, then Linear(D -> Dh)) with relu(x) + log1p(exp(-|x|));
- "first linear in the planes", all in one graph, softplus as log1p(exp(-|x|)), as the onnxruntime
  Softplus op, as relu(x) - log(sigmoid(|x|)), and with ReLU instead of softplus (not the model: the
  time of the same graph with a free activation, a bound for any softplus rewrite);
- one graph per layer with the softplus in numpy + OpenCV (what `ago export` writes and
  ago_runtime.predict.encoder runs), at several slab sizes.
sessions
- session open of planes.onnx without / with the cached optimised graph.

    python benchmarks/runtime_rewrites.py            # writes benchmarks/results/runtime_rewrites.md
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
RESULTS = REPO / "benchmarks" / "results" / "runtime_rewrites.md"


def build_variants(tmp: Path):
    import torch
    import torch.nn.functional as F
    from torch import nn

    from ago_export import graphs as G
    from ago_train.model import ModelConfig
    from ago_train.model.aggregate import upsample_planes

    cfg = ModelConfig.preset("cpu")
    cfg.pretrained = False
    torch.manual_seed(0)
    model = cfg.build().eval()
    X, Y, Z = cfg.grid_obj().shape
    D, Dh = cfg.tpv_dim, cfg.hidden_dim

    class OriginalPlanes(nn.Module):
        """The trained modules as they are, with the same outputs as PlanesGraph."""

        def __init__(self):
            super().__init__()
            self.model, self.first = model, model.decoder.net[0]

        def forward(self, images, ego2img):
            up = upsample_planes(self.model.planes(images, ego2img), self.model.grid_shape)
            return tuple(F.linear(up[p][0].permute(1, 2, 0), self.first.weight, self.first.bias if p == "xy" else None)
                         for p in ("xy", "xz", "yz"))

    class Log1pSoftplus(nn.Module):
        def forward(self, x):
            return torch.relu(x) + torch.log1p(torch.exp(-torch.abs(x)))

    class Relu(nn.Module):
        def forward(self, x):
            return torch.relu(x)

    class PerVoxelFirstLinear(nn.Module):
        """Today's voxel graph layout: planes (D, x, Y), (D, x, Z), (D, Y, Z), Linear(D -> Dh) per voxel."""

        def __init__(self):
            super().__init__()
            self.first = model.decoder.net[0]
            self.act = Log1pSoftplus()
            self.adapter = G.fused_adapter(model)
            for i, m in enumerate(self.adapter):
                if isinstance(m, G.LogSigmoidSoftplus):
                    self.adapter[i] = Log1pSoftplus()

        def forward(self, xy, xz, yz, bank_main, bank_adapted):
            vox = xy.unsqueeze(-1) + xz.unsqueeze(-2) + yz.unsqueeze(-3)
            h = self.act(self.first(vox.reshape(vox.shape[0], -1).t()))
            g = self.adapter(h)
            return h, g, torch.matmul(bank_main, h.t()), torch.matmul(bank_adapted, g.t())

    class OneGraph(nn.Module):
        """The whole per-voxel MLP in one graph (first linear in the planes), softplus as act_cls."""

        def __init__(self, act_cls):
            super().__init__()
            self.act = act_cls()
            self.adapter = G.fused_adapter(model)
            for i, m in enumerate(self.adapter):
                if isinstance(m, G.LogSigmoidSoftplus):
                    self.adapter[i] = act_cls()

        def forward(self, xy, xz, yz, bank_main, bank_adapted):
            a = xy.unsqueeze(2) + xz.unsqueeze(1) + yz.unsqueeze(0)
            h = self.act(a.reshape(-1, a.shape[-1]))
            g = self.adapter(h)
            return h, g, torch.matmul(bank_main, h.t()), torch.matmul(bank_adapted, g.t())

    def voxels_with(act_cls):
        return OneGraph(act_cls)

    images = torch.zeros(1, 6, 3, cfg.image_height, cfg.image_width)
    ego2img = torch.eye(4).expand(1, 6, 4, 4).contiguous()
    class PerCamera(G.PlanesGraph):
        """The backbone and FPN on one camera after the other (tried; not shipped)."""

        def forward(self, images, ego2img):
            per = [self.fpn(self.backbone(images[0, v:v + 1])) for v in range(images.shape[1])]
            return self.from_features([torch.cat([f[lvl] for f in per]) for lvl in range(len(per[0]))], ego2img)

    planes = {"original TPV": OriginalPlanes(), "restructured TPV (shipped)": G.PlanesGraph(model),
              "restructured TPV, backbone one camera at a time": PerCamera(model)}
    voxels = {"first linear per voxel, log1p softplus": (PerVoxelFirstLinear(), "old"),
              "first linear in the planes, log1p softplus": (voxels_with(Log1pSoftplus), "new"),
              "first linear in the planes, onnxruntime Softplus op": (voxels_with(nn.Softplus), "new"),
              "first linear in the planes, relu - log(sigmoid(|x|))": (voxels_with(G.LogSigmoidSoftplus), "new"),
              "same graph with ReLU (bound, not the model)": (voxels_with(Relu), "new")}
    out = {"planes": {}, "voxels": {}}
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        for i, (name, mod) in enumerate(planes.items()):
            path = tmp / f"planes{i}.onnx"
            torch.onnx.export(mod.eval(), (images, ego2img), str(path), dynamo=False, opset_version=17,
                              input_names=["images", "ego2img"], output_names=["plane_xy", "plane_xz", "plane_yz"])
            out["planes"][name] = path
        for i, (name, (mod, kind)) in enumerate(voxels.items()):
            path = tmp / f"voxels{i}.onnx"
            if kind == "old":
                args = (torch.zeros(D, 2, Y), torch.zeros(D, 2, Z), torch.zeros(D, Y, Z))
                axes = {"plane_xy": {1: "s"}, "plane_xz": {1: "s"}}
            else:
                args = (torch.zeros(2, Y, Dh), torch.zeros(2, Z, Dh), torch.zeros(Y, Z, Dh))
                axes = {"plane_xy": {0: "s"}, "plane_xz": {0: "s"}}
            torch.onnx.export(mod.eval(), (*args, torch.zeros(3, Dh), torch.zeros(3, cfg.adapter_hidden)), str(path),
                              dynamo=False, opset_version=17,
                              input_names=["plane_xy", "plane_xz", "plane_yz", "bank_main", "bank_adapted"],
                              output_names=["h", "g", "s_main", "s_adapted"],
                              dynamic_axes={**axes, "bank_main": {0: "p"}, "bank_adapted": {0: "p"}})
            out["voxels"][name] = (path, kind)
        stages = []
        from ago_runtime.predict.encoder import StageGraph

        for i, st in enumerate(G.voxel_stages(model)):   # bundle format 4: each stage x -> y
            path = tmp / f"stage{i}.onnx"
            torch.onnx.export(G.VoxelStageGraph(st).eval(), (torch.zeros(2, st.linear.in_features),), str(path),
                              dynamo=False, opset_version=17, input_names=["x"], output_names=["y"],
                              dynamic_axes={"x": {0: "n"}, "y": {0: "n"}})
            stages.append(StageGraph(st.spec(f"stage{i}"), path))
        out["stages"] = stages
    return cfg, out


def timed(fn, rounds: int) -> list[tuple[float, float]]:
    res = []
    for _ in range(rounds):
        w, c = time.perf_counter(), time.process_time()
        fn()
        res.append((time.perf_counter() - w, time.process_time() - c))
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    import onnxruntime as ort

    from ago_runtime.geometry.camera import Rig
    from ago_runtime.predict.encoder import open_session, session_options
    from ago_runtime.geometry.preprocess import Preprocess

    load_start = " ".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="ago_rewrites_") as tmp:
        tmp = Path(tmp)
        os.environ["AGO_CACHE_DIR"] = str(tmp / "cache")
        cfg, files = build_variants(tmp)
        rng = np.random.default_rng(0)
        x = rng.standard_normal((1, 6, 3, cfg.image_height, cfg.image_width)).astype(np.float32)
        m = Preprocess(cfg.image_width, cfg.image_height).ego2img(Rig.nuscenes_like(1600, 900))[None]
        X, Y, Z = cfg.grid_obj().shape
        psess = {k: ort.InferenceSession(str(p), session_options(), providers=["CPUExecutionProvider"])
                 for k, p in files["planes"].items()}
        outs = {k: s.run(None, {"images": x, "ego2img": m}) for k, s in psess.items()}
        ref = outs["original TPV"]
        agree = {k: max(float(np.abs(a - b).max()) for a, b in zip(o, ref)) for k, o in outs.items()}
        rows = {k: [] for k in psess}
        for _ in range(args.rounds):
            for k, s in psess.items():
                rows[k] += timed(lambda: s.run(None, {"images": x, "ego2img": m}), 1)
        planes_rows = rows
        # voxels: one frame of slabs
        new_planes = outs["restructured TPV (shipped)"]
        old_planes = [rng.standard_normal((cfg.tpv_dim, X, Y)).astype(np.float32),
                      rng.standard_normal((cfg.tpv_dim, X, Z)).astype(np.float32),
                      rng.standard_normal((cfg.tpv_dim, Y, Z)).astype(np.float32)]
        bank = {"bank_main": rng.standard_normal((35, cfg.hidden_dim)).astype(np.float32),
                "bank_adapted": rng.standard_normal((35, cfg.adapter_hidden)).astype(np.float32)}
        vsess = {k: (ort.InferenceSession(str(p), session_options(), providers=["CPUExecutionProvider"]), kind)
                 for k, (p, kind) in files["voxels"].items()}

        def frame(s, kind, voxels):
            rows_per = max(1, voxels // (Y * Z))
            for x0 in range(0, X, rows_per):
                if kind == "old":
                    feeds = {"plane_xy": np.ascontiguousarray(old_planes[0][:, x0:x0 + rows_per]),
                             "plane_xz": np.ascontiguousarray(old_planes[1][:, x0:x0 + rows_per]), "plane_yz": old_planes[2]}
                else:
                    feeds = {"plane_xy": new_planes[0][x0:x0 + rows_per], "plane_xz": new_planes[1][x0:x0 + rows_per],
                             "plane_yz": new_planes[2]}
                s.run(["s_main", "s_adapted"], {**feeds, **bank})

        from ago_runtime.predict.encoder import SplitEncoder
        from ago_runtime.geometry.grid import Grid

        from ago_runtime.predict.contract import Branch

        stages = files["stages"]
        hidden_dim = next(st.spec.input_dim for st in stages if st.spec.branch == Branch.ADAPTED)
        enc = SplitEncoder(files["planes"]["restructured TPV (shipped)"], stages, Grid.from_dict(cfg.grid),
                           hidden_dim, stages[-1].spec.output_dim, warm_up=False)
        fold = {"main": bank["bank_main"], "adapted": bank["bank_adapted"]}

        def staged(voxels):
            rows_per = enc.rows_per_slab(voxels)
            for x0 in range(0, X, rows_per):   # both branches on every voxel, as the one-graph variants
                h = enc.hidden_slab(new_planes, x0, min(X, x0 + rows_per))
                enc.scores(fold["main"], h)
                enc.scores(fold["adapted"], enc.adapted_hidden(h))

        cases = {k: (lambda s=s, kind=kind: frame(s, kind, 65536 if kind == "old" else 8192)) for k, (s, kind) in vsess.items()}
        for v in (2048, 4096, 8192, 16384, 65536):
            name = "one graph per layer, softplus in numpy + OpenCV" + (" (shipped)" if v == 4096 else "")
            cases[f"{name}, slabs of {v} voxels"] = (lambda v=v: staged(v))
        vrows = {k: [] for k in cases}
        for fn in cases.values():
            fn()
        for _ in range(args.rounds):
            for k, fn in cases.items():
                vrows[k] += timed(fn, 1)
        # session open without / with the cached optimised graph
        path = files["planes"]["restructured TPV (shipped)"]
        sha = __import__("hashlib").sha256(path.read_bytes()).hexdigest()
        open_rows = {"no cache (optimise the graph)": [], "cached optimised graph": []}
        open_session(path, None, sha)   # writes the cache
        for _ in range(max(2, args.rounds // 2)):
            open_rows["no cache (optimise the graph)"] += timed(lambda: open_session(path, None, None), 1)
            open_rows["cached optimised graph"] += timed(lambda: open_session(path, None, sha), 1)
    load_end = " ".join(f"{x:.2f}" for x in os.getloadavg())

    def fmt(v):
        v = np.array(v) * 1e3
        return f"{v[:, 0].min():.0f} | {np.median(v[:, 0]):.0f} | {v[:, 1].min():.0f} | {np.median(v[:, 1]):.0f}"

    L = ["# What each rewrite buys (A/B in one process)\n",
         f"Command: `python benchmarks/runtime_rewrites.py --rounds {args.rounds}`; load average at start {load_start}, "
         f"at end {load_end} (shared machine: compare within a table; the minimum is the least disturbed run). "
         "Model: the cpu preset with random weights (100x100x8, 352x192 images); bank of 35 phrases.\n",
         "## planes.onnx (one frame)\n",
         "| variant | wall min ms | wall median ms | CPU min ms | CPU median ms | max abs diff to the original |",
         "|---|---|---|---|---|---|"]
    for k, v in planes_rows.items():
        L.append(f"| {k} | {fmt(v)} | {agree[k]:.1e} |")
    L += ["\n## Voxel stage (one frame of slabs; one-graph variants in slabs of 8192 voxels, the per-voxel layout in 65 536)\n",
          "| variant | wall min ms | wall median ms | CPU min ms | CPU median ms |", "|---|---|---|---|---|"]
    for k, v in vrows.items():
        L.append(f"| {k} | {fmt(v)} |")
    L += ["\n## Session open of planes.onnx\n", "| variant | wall min ms | wall median ms | CPU min ms | CPU median ms |",
          "|---|---|---|---|---|"]
    for k, v in open_rows.items():
        L.append(f"| {k} | {fmt(v)} |")
    text = "\n".join(L) + "\n"
    from ago_runtime.atomic import write_text

    write_text(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
