"""How well can the adapted branch read classes at best? Nearest-text accuracy of the lifted image
embeddings E_3D themselves under several read-outs (the ceiling of an adapter that matched E_3D exactly).

    python benchmarks/e3d_readout.py --data work/db24/synth --pseudo work/db24/pseudo_ow \
        [--prompts prompts/ow.txt] [--frames 40] [--out benchmarks/results/e3d_readout.md]

For every `--frames`-th frame of the pseudo-label folder (training split; the statistics mu_E / mu_T
below are fitted on the other frames), each voxel with an E_3D is given the most frequent non-free GT
class of its 2x2x2 block of the 200x200x16 Occ3D GT (voxels whose block is all free are skipped).
Read-outs, each argmax over the 15 classes of prompts/ow.txt (a class scores the max over its phrases):
  raw         cos(E, t_k)                    (the paper's P~ if F~_3D = E_3D)
  centred E   cos(E - mu_E, t_k)              (align_center: mu_E = mean E_3D of training voxels)
  centred E,T cos(E - mu_E, t_k - mu_T)       (mu_T = mean of the bank's phrase embeddings)
Reported: per class accuracy (share of its voxels read as that class), mean over the unknown
classes of the zero-shot split, mean over all 15.
"""
from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

UNKNOWN = ("barrier", "traffic_cone", "terrain", "manmade", "vegetation")


def block_labels(gt: np.ndarray, shape) -> np.ndarray:
    """(200,200,16) Occ3D ids -> (X,Y,Z) most frequent non-free id per block (255 if all free)."""
    fx, fy, fz = (g // s for g, s in zip(gt.shape, shape))
    b = gt.reshape(shape[0], fx, shape[1], fy, shape[2], fz).transpose(0, 2, 4, 1, 3, 5).reshape(*shape, -1)
    out = np.full(shape, 255, np.uint8)
    counts = np.zeros((*shape, 17), np.int32)
    for c in range(17):
        counts[..., c] = (b == c).sum(-1)
    has = counts.sum(-1) > 0
    out[has] = counts.argmax(-1)[has]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--pseudo", required=True)
    ap.add_argument("--prompts", default=str(REPO / "prompts/ow.txt"))
    ap.add_argument("--frames", type=int, default=8, help="score every N-th frame, fit mu on the rest")
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/e3d_readout.md"))
    a = ap.parse_args(argv)
    from ago_runtime.formats.occ3d import labels_path, load_semantics
    from ago_runtime.vocab import load_prompt_bank
    from ago_train.pseudo.generate import PseudoLabelDir

    ps = PseudoLabelDir(a.pseudo)
    bank = load_prompt_bank(a.prompts)
    names = list(bank.class_names)
    T = np.asarray(bank.embeddings, np.float64)
    pc = np.asarray(bank.phrase_class)
    frames = ps.samples()
    grid_shape = tuple(ps.grid.shape)
    held, fit = frames[:: a.frames], [f for i, f in enumerate(frames) if i % a.frames]
    s, n = 0.0, 0
    for scene, tok in fit[:: 4]:
        _, e = ps.embeds(scene, tok)
        s = s + e.astype(np.float64).sum(0); n += len(e)
    mu_e = s / n
    mu_t = T.mean(0)
    from ago_train.text.noise import default_noise_bank_path
    mu_noise = np.load(default_noise_bank_path())["embeddings"].astype(np.float64).mean(0)
    mu_pre = np.asarray(load_prompt_bank(REPO / "prompts/ow_pretrain.txt").embeddings, np.float64).mean(0)
    from ago_runtime.classes import OCC3D_ID
    occ_of_class = np.array([OCC3D_ID[c] for c in names])
    lut = np.full(256, -1, np.int64)
    lut[occ_of_class] = np.arange(len(names))
    # read-out name -> (vector subtracted from E, vector subtracted from every phrase embedding)
    reads = {"raw": (0.0, 0.0), "centred E": (mu_e, 0.0), "centred E, T - mean(eval bank)": (mu_e, mu_t),
             "centred E, T - mean(noise words)": (mu_e, mu_noise),
             "E - mu_E + mean(noise words)": (mu_e - mu_noise, 0.0),
             "E - mu_E + mean(pretrain bank)": (mu_e - mu_pre, 0.0)}
    hits = {r: np.zeros(len(names)) for r in reads}
    tot = np.zeros(len(names))
    for scene, tok in held:
        idx, e = ps.embeds(scene, tok)
        gt, _ = load_semantics(labels_path(Path(a.data) / "gts", scene, tok))
        lab = lut[block_labels(gt, grid_shape).reshape(-1)[idx]]
        keep = lab >= 0
        lab, e = lab[keep], e[keep].astype(np.float64)
        np.add.at(tot, lab, 1)
        for r, (me, mt) in reads.items():
            x = e - me
            x /= np.linalg.norm(x, axis=1, keepdims=True) + 1e-9
            t = T - mt
            t /= np.linalg.norm(t, axis=1, keepdims=True) + 1e-9
            ph = x @ t.T
            cls = np.full((len(x), len(names)), -np.inf)
            for k in range(len(names)):
                cls[:, k] = ph[:, pc == k].max(1)
            np.add.at(hits[r], lab, cls.argmax(1) == lab)
    unk = [names.index(c) for c in UNKNOWN if c in names]
    lines = [f"# Read-out ceiling of the adapted branch: E_3D's own nearest-text accuracy", "",
             f"Command: `python benchmarks/{Path(__file__).name} {' '.join(shlex.quote(x) for x in (argv or sys.argv[1:]))}`", "",
             f"{len(held)} held-out frames of `{a.pseudo}` (mu_E from {len(fit[::4])} other frames); "
             f"{int(tot.sum())} voxels; simulated VLM embeddings (a simulation, docs/synth.md).", "",
             "| read-out | " + " | ".join(names) + " | mean unknown | mean all |",
             "|---|" + "---:|" * (len(names) + 2)]
    for r in reads:
        acc = hits[r] / np.maximum(tot, 1)
        lines.append(f"| {r} | " + " | ".join(f"{100 * v:.0f}" for v in acc)
                     + f" | {100 * acc[unk].mean():.1f} | {100 * acc[tot > 0].mean():.1f} |")
    lines.append("| voxels | " + " | ".join(str(int(v)) for v in tot) + " | | |")
    text = "\n".join(lines) + "\n"
    print(text)
    Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
