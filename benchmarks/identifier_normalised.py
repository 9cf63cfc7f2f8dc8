"""Diagnostic (not the shipped identifier): min-entropy with each branch's entropy divided by its typical entropy.

    python benchmarks/identifier_normalised.py RUN_DIR PROMPTS_WITH_KNOWN [--out benchmarks/results/identifier_normalised.md]

The typical entropy of a branch is its mean class entropy (calibrated softmax over the evaluation
prompt space) on voxels of the training label space's classes in every 12th TRAINING frame: no val
data, no GT, no unknown-class labels. The rule: a voxel takes the adapted branch when
H(P~) / mean_H(P~) < H(P) / mean_H(P). It is evaluated on the val split of the default-bundle town
by patching ago_train.experiments.scoring's identifier (a measurement of a lead for issue "Open world
that works", not a change of the model or the runtime).
"""
import sys
import torch
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ago_train.train_config import TrainConfig
from ago_train.trainer import Trainer
from ago_train.dataset import collate
from ago_train.model.scoring import class_logits, entropy
from ago_train.evaluate import checkpoint_scales
from ago_train.experiments import scoring as S
from ago_train.checkpoint import load_checkpoint
run = Path(sys.argv[1]); prompts = sys.argv[2]
out_md = Path(sys.argv[4]) if len(sys.argv) > 4 and sys.argv[3] == "--out" else Path("/work/main/benchmarks/results/identifier_normalised.md")
cfg = TrainConfig.load(run / "config.json")
t = Trainer(cfg, resume=True, quiet=True); t.setup(); t.model.eval(); t.dataset.augment = "none"
ckpt = load_checkpoint(run / "last.pt", map_location="cpu")
sm, sa = checkpoint_scales(ckpt)
bank = S._bank(ckpt, prompts, False)
K15 = bank.space.num_classes
K5 = t.label_space.num_classes
hm, ha = [], []
with torch.no_grad():
    for i in range(0, len(t.dataset), 12):
        b = collate([t.dataset[i]])
        sem = b["semantics"][0].reshape(-1)
        cand = torch.nonzero(sem < K5).reshape(-1)[:4000]
        prefix = [p.reshape(-1, *p.shape[2:]).float() for p in b["prefix"]] if "prefix" in b else None
        out = t.model(b.get("images"), b["ego2img"], cand[None], prefix, adapted=True)
        free = out["free_embedding"]
        lm = class_logits(out["feat"], bank.text, bank.phrase_class, K15, free, None)[0, :, :K15]
        la = class_logits(out["feat_adapted"], bank.text, bank.phrase_class, K15, free, None)[0, :, :K15]
        hm.append(entropy(torch.softmax(sm * lm, -1))); ha.append(entropy(torch.softmax(sa * la, -1)))
Hm, Ha = float(torch.cat(hm).mean()), float(torch.cat(ha).mean())
print("typical entropy on known training voxels: main", Hm, "adapted", Ha)
orig = S.open_world_identify
def patched(lm, la, mode="min-entropy", num_classes=None, scale_main=1.0, scale_adapted=1.0):
    if mode != "min-entropy":
        return orig(lm, la, mode, num_classes, scale_main, scale_adapted)
    K = num_classes
    occupied = lm[..., :K + 1].argmax(-1) != K
    pm = torch.softmax(scale_main * lm[..., :K].float(), -1); pa = torch.softmax(scale_adapted * la[..., :K].float(), -1)
    use = (entropy(pa) / Ha < entropy(pm) / Hm) & occupied
    cls = torch.where(use, pa.argmax(-1), pm.argmax(-1))
    return torch.where(occupied, cls, torch.full_like(cls, K)), use.long(), None
S.open_world_identify = patched
r = S.evaluate_views(run / "last.pt", str(Path(cfg.data)), [S.View("ne", prompts, "min-entropy")], quiet=True)
v = r["views"]["ne"]
row = (f"| `{run}` | {Hm:.3f} | {Ha:.3f} | {v['subsets']['known']} | {v['subsets']['unknown']} | {v['mIoU']} | "
       + " / ".join(str(v["metric"]["iou"][k]) for k in ("barrier", "traffic_cone", "terrain", "manmade", "vegetation")) + " |")
print(row)
head = ("# Normalised min-entropy identifier (diagnostic)\n\nCommand: `python benchmarks/identifier_normalised.py RUN_DIR PROMPTS_WITH_KNOWN` (val split of the run data), "
        "one row per run (rows are appended).\n\n| run | typical H(P) | typical H(P~) | known mIoU | unknown mIoU | mIoU | "
        "barrier / traffic cone / terrain / manmade / vegetation IoU |\n|---|---:|---:|---:|---:|---:|---|\n")
text = out_md.read_text() if out_md.is_file() else head
text = "\n".join(l for l in text.splitlines() if not l.startswith(f"| `{run}` |")) + "\n" + row + "\n"
out_md.write_text(text)
