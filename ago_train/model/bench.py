"""Time a training step (forward + backward) of a model preset on this machine.

    python -m ago_train.model.bench --preset cpu [--voxels 8000] [--threads 2] [--steps 5] [--set k=v ...]

`--voxels M` runs the voxel heads on a sample of M voxels (as training does with
ago_train.losses.sampling.select_training_voxels); 0 = the full grid. Prints the median step time
and its parts (backbone+FPN, TPV encoder, voxel heads + a dummy loss, backward) in seconds, plus
the step's process CPU time (step_cpu_s; with --threads 1 it is what an idle machine's wall time
would be, even while other jobs share the cores).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from ago_runtime.geometry.camera import Rig

from .config import ModelConfig


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--voxels", type=int, default=8000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--pretrained", action="store_true", help="load ImageNet weights (same speed)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="override integer config fields, e.g. --set frozen_stages=2 tpv_dim=48")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = ModelConfig.preset(args.preset)
    cfg.pretrained = args.pretrained and cfg.pretrained
    for item in args.set:
        key, value = item.split("=", 1)
        setattr(cfg, key, int(value))
    cfg.validate()
    model = cfg.build().train()
    images = torch.randn(1, cfg.num_cameras, 3, cfg.image_height, cfg.image_width)
    ego2img = torch.from_numpy(Rig.nuscenes_like(cfg.image_width, cfg.image_height).ego2img())[None]
    index = None
    if args.voxels:
        index = torch.randperm(model.num_voxels)[: args.voxels][None]
    from .aggregate import planes_at_voxels, planes_to_voxels

    rows = []
    for _ in range(args.steps + 1):
        c0 = time.process_time()
        t0 = time.perf_counter()
        B, V = images.shape[:2]
        feats = model.fpn(model.backbone(images.reshape(B * V, *images.shape[2:])))
        t1 = time.perf_counter()
        planes = model.encoder(feats, ego2img)
        t2 = time.perf_counter()
        vox = planes_to_voxels(planes, model.grid_shape) if index is None else \
            planes_at_voxels(planes, model.grid_shape, index)
        feat = model.decoder_out(model.decoder(vox))
        adapted = model.adapter_out(model.adapter(feat))
        loss = feat.square().mean() + adapted.square().mean()
        t3 = time.perf_counter()
        loss.backward()
        t4 = time.perf_counter()
        model.zero_grad(set_to_none=True)
        rows.append((t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0, time.process_time() - c0))
    rows = rows[1:]  # the first step warms up
    med = [statistics.median(r[i] for r in rows) for i in range(6)]
    result = {"preset": args.preset, "voxels": args.voxels or model.num_voxels, "threads": args.threads,
              "backbone_fpn_s": med[0], "encoder_s": med[1], "heads_s": med[2], "backward_s": med[3],
              "step_s": med[4], "step_cpu_s": med[5]}
    print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in result.items()))
    return result


if __name__ == "__main__":
    main()
