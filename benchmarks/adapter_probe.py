"""Where is the unknown-class information lost? Linear probes along the open-world model's voxel path.

    python benchmarks/adapter_probe.py RUN_DIR --val-pseudo PSEUDO_VAL [--frames 24] [--out FILE.md]

RUN_DIR: an `ago train` folder of the open-world pretraining (5 classes, variant "ago").
For every few training frames (fit) and val frames (test) the model's per-voxel tensors are taken at
the voxels that have a lifted image embedding E_3D: the TPV feature, the decoder hidden h, F_3D and
the adapter's F~_3D. Each voxel's class is the most frequent non-free GT class of its 2x2x2 block
(used only to SCORE, never to fit). A ridge regression from each tensor to the alignment target
(E_3D minus the run's align centre, or E_3D) is fitted on the training voxels, and each probe's
output, the adapter's own output and the target itself are read against prompts/ow.txt (argmax over
the 15 classes, a class scoring the max over its phrases, cosine). Reported on val voxels: per-class
nearest-text accuracy, the mean over the unknown classes, and the cosine of each to the target.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

UNKNOWN = ("barrier", "traffic_cone", "terrain", "manmade", "vegetation")


def collect(trainer, gts_root: Path, every: int, lut: np.ndarray) -> dict:
    from e3d_readout import block_labels
    from ago_runtime.formats.occ3d import labels_path, load_semantics
    from ago_train.dataset import collate

    model, ds = trainer.model, trainer.dataset
    ds.augment = "none"
    cols = {k: [] for k in ("tpv", "h", "F", "Fa", "E", "y")}
    with torch.no_grad():
        for i in range(0, len(ds), every):
            b = collate([ds[i]])
            idx = b["align_index"].long()
            if idx.numel() == 0:
                continue
            prefix = [p.reshape(-1, *p.shape[2:]).float() for p in b["prefix"]] if "prefix" in b else None
            tpv = model.voxel_features(b.get("images"), b["ego2img"], idx[None], prefix)[0]
            h = model.decoder(tpv)
            F = model.decoder_out(h)
            gt, _ = load_semantics(labels_path(gts_root, b["scene"][0], b["token"][0]))
            y = lut[block_labels(gt, trainer.grid.shape).reshape(-1)[idx.numpy()]]
            for k, v in (("tpv", tpv), ("h", h), ("F", F), ("Fa", model.adapt(F)), ("E", b["align_embed"])):
                cols[k].append(v.numpy().astype(np.float64))
            cols["y"].append(y)
    return {k: np.concatenate(v) for k, v in cols.items()}


def read(x: np.ndarray, T: np.ndarray, pc: np.ndarray, K: int) -> np.ndarray:
    x = x / (np.linalg.norm(x, axis=1, keepdims=True) + 1e-9)
    ph = x @ (T / np.linalg.norm(T, axis=1, keepdims=True)).T
    return np.stack([ph[:, pc == k].max(1) for k in range(K)], 1).argmax(1)


def read_standardised(x: np.ndarray, ref: np.ndarray, T: np.ndarray, pc: np.ndarray, K: int) -> np.ndarray:
    """Dot products with each phrase, standardised by that phrase's score mean and std over `ref`
    (embeddings of training voxels, no labels): z = (x.t - m.t) / sqrt(t' S t)."""
    m = ref.mean(0)
    S = np.cov(ref, rowvar=False)
    sd = np.sqrt(np.einsum("pc,cd,pd->p", T, S, T))
    z = (x @ T.T - (m @ T.T)[None]) / sd[None]
    return np.stack([z[:, pc == k].max(1) for k in range(K)], 1).argmax(1)


def ridge(X: np.ndarray, Y: np.ndarray, lam: float = 1e-2):
    mx, my = X.mean(0), Y.mean(0)
    Xc = X - mx
    A = Xc.T @ Xc / len(X)
    W = np.linalg.solve(A + lam * np.trace(A) / len(A) * np.eye(len(A)), Xc.T @ (Y - my) / len(X))
    return lambda Z: (Z - mx) @ W + my


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--val-pseudo", required=True)
    ap.add_argument("--every", type=int, default=8)
    ap.add_argument("--checkpoint", default="last.pt")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    from ago_runtime.classes import OCC3D_ID
    from ago_runtime.vocab import load_prompt_bank
    from ago_train.checkpoint import load_checkpoint, load_model_weights
    from ago_train.train_config import TrainConfig
    from ago_train.trainer import Trainer

    run = Path(a.run)
    cfg = TrainConfig.load(run / "config.json")
    bank = load_prompt_bank(REPO / "prompts/ow.txt")
    names = list(bank.class_names)
    T, pc, K = np.asarray(bank.embeddings, np.float64), np.asarray(bank.phrase_class), len(names)
    lut = np.full(256, -1, np.int64)
    lut[[OCC3D_ID[c] for c in names]] = np.arange(K)
    ckpt = load_checkpoint(run / a.checkpoint, map_location="cpu")

    def trainer_for(split_cfg):
        t = Trainer(split_cfg, resume=False, quiet=True)
        t.setup()
        load_model_weights(t.model, ckpt, str(run / a.checkpoint), cfg.model.to_dict(), what="probe")
        t.model.eval()
        return t

    tr = trainer_for(cfg)
    center = tr.align_center.numpy().astype(np.float64) if tr.align_center is not None else np.zeros(T.shape[1])
    fit = collect(tr, Path(cfg.data) / "gts", a.every, lut)
    vcfg = TrainConfig.load(run / "config.json")
    vcfg.train_split, vcfg.pseudo, vcfg.feature_cache = "val", a.val_pseudo, "off"
    val = collect(trainer_for(vcfg), Path(cfg.data) / "gts", max(1, a.every // 2), lut)
    target_fit, target_val = fit["E"] - center, val["E"] - center
    outputs = {"target E_3D - centre": target_val, "adapter F~_3D": val["Fa"]}
    for src in ("F", "h", "tpv"):
        outputs[f"ridge probe {src} -> target"] = ridge(fit[src], target_fit)(val[src])
    refs = {"adapter F~_3D": fit["Fa"], "target E_3D - centre": target_fit}
    unk = [names.index(c) for c in UNKNOWN]
    y = val["y"]
    rows = []
    readouts = [(n, x, None) for n, x in outputs.items()] + [
        (n + ", phrase-standardised", outputs[n], r) for n, r in refs.items()]
    for name, x, ref in readouts:
        pred = read(x, T, pc, K) if ref is None else read_standardised(x, ref, T, pc, K)
        acc = np.array([(pred[y == k] == k).mean() if (y == k).any() else np.nan for k in range(K)])
        cos = np.mean(np.sum(x * target_val, 1) / (np.linalg.norm(x, axis=1) * np.linalg.norm(target_val, axis=1) + 1e-9))
        rows.append((name, acc, cos))
    cmd = f"python benchmarks/{Path(__file__).name} " + " ".join(shlex.quote(s) for s in (argv or sys.argv[1:]))
    lines = ["# Adapter probe: where the unknown-class information is lost", "", f"Command: `{cmd}`", "",
             f"Run `{run}` ({a.checkpoint}); fit on {len(fit['y'])} training voxels, scored on {len(y)} val voxels "
             f"(`{a.val_pseudo}`); simulated VLM embeddings.", "",
             "| output | " + " | ".join(names) + " | mean unknown | mean all | cos to target |",
             "|---|" + "---:|" * (K + 3)]
    for name, acc, cos in rows:
        lines.append(f"| {name} | " + " | ".join("-" if np.isnan(v) else f"{100 * v:.0f}" for v in acc)
                     + f" | {100 * np.nanmean(acc[unk]):.1f} | {100 * np.nanmean(acc):.1f} | {cos:.3f} |")
    lines.append("| val voxels | " + " | ".join(str(int((y == k).sum())) for k in range(K)) + " | | | |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
