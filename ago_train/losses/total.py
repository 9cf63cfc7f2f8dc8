"""The AGO training objective and its ablation variants.

`compute_losses(outputs, batch, bank, cfg)`:
- outputs: AGOModel.forward's dict: "feat" F_3D (B, N|M, C), "feat_adapted" F~_3D (B, N|M, C),
  "free_embedding" (C,), and "voxel_index" (B, M) when the model ran on a voxel sample.
- batch: "semantics" (B, X, Y, Z) or (B, N) pseudo-labels (0..K-1, 17 free, 255 unknown);
  for the align variants "align_index" (Ma,) int64 flat indices into the batch's B*N voxels
  (b * N + voxel) and "align_embed" (Ma, C) their E_3D embeddings (visible occupied voxels).
- bank: `BankTensors` (text (P, C), phrase_class (P,), num_classes K, noise (Nn, C) or None).
- batch may hold "align_center" (C,): subtracted from E_3D before the alignment loss (LossConfig.align_center).
- class_weight: (K + 1,) CE weights of the classes and free (LossConfig.class_balance), or None.
- sample_weight: (B, M) importance weights of a stratified voxel sample (losses/sampling.py), or None:
  every loss is then the weighted mean over the sampled voxels (an estimate of its whole-grid value).
Returns a dict of scalar tensors: "total" plus the parts that were computed
("grounding_ce", "grounding_lovasz", "occ", "align", "unlabelled_uniform").

Variants (`LossConfig.variant`):
- "align":            align(F_3D, E_3D) (+ occ) (no adapter, no grounding): the POP-3D-like baseline.
                      POP-3D learns occupancy with its own head; here the 2-way occupancy CE on
                      [max over class texts ; free] stands in for it (it says only occupied vs free,
                      never which class), so the baseline predicts geometry and takes its classes
                      purely from the alignment. `use_occ=False` gives alignment alone;
- "grounding":        grounding (+ occ) on F_3D only;
- "grounding+align":  grounding (+ occ) on F_3D and align(F_3D, E_3D);
- "ago":              grounding (+ occ) on F_3D and align(F~_3D, E_3D)  (the paper).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from ago_runtime.classes import OCCUPIED_UNLABELLED
from ago_train.model.text_logits import class_logits

from .align import ALIGN_LOSSES, align_loss
from .grounding import grounding_loss, semantics_to_targets
from .occupancy import occupancy_binary, occupancy_loss

VARIANTS = ("align", "grounding", "grounding+align", "ago")


@dataclass
class LossConfig:
    variant: str = "ago"
    use_noise: bool = True      # noise-word columns as negatives in the grounding softmax
    use_occ: bool = True        # add the 2-way occupancy CE
    align_loss: str = "cosine"  # "cosine" | "mse" | "l1"
    w_ce: float = 1.0
    w_lovasz: float = 1.0
    w_occ: float = 1.0
    w_align: float = 1.0
    lovasz_only_present: bool = True
    # Departure from the paper (docs/training.md, "open world"): align F~_3D with E_3D minus the mean
    # E_3D of the training frames. The simulated (and CLIP-like) image embeddings share one large
    # offset; under a cosine loss that offset dominates and the adapter learns little else.
    align_center: bool = False
    # Departure from the paper (docs/training.md, "Class balance"): CE weights n_c ** -class_balance of the
    # occupied classes' voxel counts in the training pseudo-labels (losses/class_balance.py); 0 = uniform.
    class_balance: float = 0.0
    # Departure from the paper (docs/training.md, "open world"): on voxels the LiDAR hit that no mask of
    # the label space labelled (OCCUPIED_UNLABELLED: matter of no training class, or a missed instance),
    # push F_3D's softmax over [the K class texts + the noise words] towards uniform (cross-entropy to the
    # uniform distribution, as outlier exposure does). The grounded branch then stays unsure on matter
    # of no training class, and the min-entropy identifier can hand those voxels to F~_3D. 0 = off.
    # Uses no class label: only "hit, and no training class's mask covers it".
    w_unlabelled_uniform: float = 0.0
    # Departure from the paper (docs/training.md, "open world"): the occupancy loss of those voxels
    # (OCCUPIED_UNLABELLED) weighs this many times a labelled voxel's. A labelled occupied voxel is told
    # "occupied" by three losses (CE, Lovász, occupancy), a hit-unlabelled one by the occupancy loss alone,
    # and with a small label space most occupied matter is unlabelled: at 1.0 the open-world pretraining
    # learnt to call it free (docs/results.md). 1.0 = the paper's.
    occ_unlabelled_weight: float = 1.0

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown loss variant {self.variant!r}; expected one of {VARIANTS}")
        if self.align_loss not in ALIGN_LOSSES:
            raise ValueError(f"unknown align loss {self.align_loss!r}; expected one of {ALIGN_LOSSES}")
        if isinstance(self.w_unlabelled_uniform, bool) or not isinstance(self.w_unlabelled_uniform, (int, float)) \
                or float(self.w_unlabelled_uniform) < 0:
            raise ValueError(f"loss.w_unlabelled_uniform must be a number >= 0, got {self.w_unlabelled_uniform!r}")
        if isinstance(self.occ_unlabelled_weight, bool) or not isinstance(self.occ_unlabelled_weight, (int, float)) \
                or float(self.occ_unlabelled_weight) <= 0:
            raise ValueError(f"loss.occ_unlabelled_weight must be a number > 0, got {self.occ_unlabelled_weight!r}")
        if isinstance(self.class_balance, bool) or not isinstance(self.class_balance, (int, float)) \
                or not 0.0 <= float(self.class_balance) <= 2.0:
            raise ValueError(f"loss.class_balance must be a number in 0..2, got {self.class_balance!r}")

    @property
    def uses_grounding(self) -> bool:
        return self.variant != "align"

    @property
    def uses_align(self) -> bool:
        return self.variant != "grounding"

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LossConfig":
        return cls(**d)


@dataclass
class BankTensors:
    """A text bank as torch tensors: phrase embeddings, their class ids, the class count, noise words."""

    text: torch.Tensor            # (P, C) float32
    phrase_class: torch.Tensor    # (P,) int64 in 0..K-1
    num_classes: int              # K
    noise: torch.Tensor | None = None  # (Nn, C) float32

    @classmethod
    def from_arrays(cls, text, phrase_class, num_classes: int, noise=None, device="cpu") -> "BankTensors":
        t = torch.as_tensor(text, dtype=torch.float32, device=device)
        pc = torch.as_tensor(phrase_class, dtype=torch.long, device=device)
        n = None if noise is None else torch.as_tensor(noise, dtype=torch.float32, device=device)
        return cls(t, pc, int(num_classes), n)

    def to(self, device) -> "BankTensors":
        return BankTensors(self.text.to(device), self.phrase_class.to(device), self.num_classes,
                           None if self.noise is None else self.noise.to(device))


def _sampled(values: torch.Tensor, outputs: dict) -> torch.Tensor:
    """(B, N) per-voxel values -> (B, N|M): those of the voxels the losses see (the voxel sample, if any)."""
    if "voxel_index" not in outputs:
        return values
    vi = outputs["voxel_index"]
    if vi.dim() == 1:
        vi = vi.unsqueeze(0).expand(values.shape[0], -1)
    return torch.gather(values, 1, vi)


def _flat_targets(batch: dict, outputs: dict, num_classes: int) -> torch.Tensor:
    B = outputs["feat"].shape[0]
    sem = batch["semantics"].reshape(B, -1)
    return _sampled(semantics_to_targets(sem, num_classes).to(outputs["feat"].device), outputs)


def _flat_semantics(batch: dict, outputs: dict) -> torch.Tensor:
    """(B, N|M) raw pseudo semantics of the voxels the losses see."""
    B = outputs["feat"].shape[0]
    return _sampled(batch["semantics"].reshape(B, -1).to(outputs["feat"].device).long(), outputs)


def unlabelled_uniform_loss(logits: torch.Tensor, semantics: torch.Tensor, num_classes: int,
                            weight: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy between the uniform distribution and softmax over the class and noise columns of
    `logits` (.., K + 1 + Nn) (the free column K is left out: occupancy has its own loss), averaged over
    the voxels whose pseudo semantics are OCCUPIED_UNLABELLED (weighted by `weight` when given), minus
    its minimum log(K + Nn), so 0 means "uniform". 0 when there is no such voxel."""
    K = num_classes
    cols = torch.cat([logits[..., :K], logits[..., K + 1:]], -1).float()
    sel = semantics == OCCUPIED_UNLABELLED
    if not bool(sel.any()):
        return logits.sum() * 0.0
    logp = torch.log_softmax(cols[sel], -1)
    per_voxel = -logp.mean(-1) - torch.log(torch.tensor(float(cols.shape[-1]), device=logp.device))
    if weight is None:
        return per_voxel.mean()
    w = weight[sel].float()
    return (w * per_voxel).sum() / w.sum().clamp_min(1e-12)


def _flat_occupancy(batch: dict, outputs: dict, num_classes: int) -> torch.Tensor:
    """(B, N|M) 0 occupied / 1 free / IGNORE from the pseudo semantics (hit-unlabelled voxels occupied)."""
    B = outputs["feat"].shape[0]
    binary = occupancy_binary(batch["semantics"].reshape(B, -1), num_classes).to(outputs["feat"].device)
    return _sampled(binary, outputs)


def _align_rows(batch: dict, outputs: dict, num_voxels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """-> (rows into the flattened (B*N or B*M) features, E_3D rows) of the align voxels present."""
    idx = batch["align_index"].long().to(outputs["feat"].device)
    emb = batch["align_embed"].to(outputs["feat"].device)
    if "voxel_index" not in outputs:
        return idx, emb
    vi = outputs["voxel_index"]
    B = outputs["feat"].shape[0]
    if vi.dim() == 1:
        vi = vi.unsqueeze(0).expand(B, -1)
    M = vi.shape[1]
    inverse = torch.full((B * num_voxels,), -1, dtype=torch.long, device=idx.device)
    full = (torch.arange(B, device=idx.device)[:, None] * num_voxels + vi).reshape(-1)
    inverse[full] = torch.arange(B * M, device=idx.device)
    rows = inverse[idx]
    keep = rows >= 0          # align voxels outside the sample are skipped
    return rows[keep], emb[keep]


def _occupancy_weight(w: torch.Tensor | None, batch: dict, outputs: dict, cfg: LossConfig) -> torch.Tensor | None:
    """The occupancy loss's per-voxel weights: the sample weights, times cfg.occ_unlabelled_weight on
    OCCUPIED_UNLABELLED voxels."""
    if cfg.occ_unlabelled_weight == 1.0:
        return w
    sem = _flat_semantics(batch, outputs)
    factor = torch.where(sem == OCCUPIED_UNLABELLED, float(cfg.occ_unlabelled_weight), 1.0).to(outputs["feat"].dtype)
    return factor if w is None else w * factor


def compute_losses(outputs: dict, batch: dict, bank: BankTensors, cfg: LossConfig,
                   free_embedding: torch.Tensor | None = None, num_voxels: int | None = None,
                   sample_weight: torch.Tensor | None = None, adapter=None,
                   class_weight: torch.Tensor | None = None) -> dict:
    """See the module docstring. `num_voxels` (N of the grid) is needed only with a voxel sample
    ("voxel_index" in outputs) and align; by default it is read from batch["semantics"].
    `adapter` (F_3D rows -> F~_3D rows, e.g. AGOModel.adapt): when outputs hold no "feat_adapted", the
    "ago" variant runs it on the align voxels only (the same values, fewer rows).
    `class_weight` (K + 1,): the grounding CE's class weights (LossConfig.class_balance), or None."""
    feat = outputs["feat"]
    free = free_embedding if free_embedding is not None else outputs["free_embedding"]
    K = bank.num_classes
    w = None if sample_weight is None else sample_weight.to(feat.device).reshape(feat.shape[0], -1)
    losses: dict[str, torch.Tensor] = {}
    total = feat.sum() * 0.0
    if cfg.uses_grounding:
        target = _flat_targets(batch, outputs, K)
        noise = bank.noise if cfg.use_noise else None
        logits = class_logits(feat, bank.text, bank.phrase_class, K, free, noise, free_bias=outputs.get("free_bias"))
        ce, lov = grounding_loss(logits, target, K, cfg.lovasz_only_present, weight=w, class_weight=class_weight)
        losses["grounding_ce"], losses["grounding_lovasz"] = ce, lov
        total = total + cfg.w_ce * ce + cfg.w_lovasz * lov
        if cfg.use_occ:
            losses["occ"] = occupancy_loss(logits, target, K, weight=_occupancy_weight(w, batch, outputs, cfg),
                                           binary=_flat_occupancy(batch, outputs, K))
            total = total + cfg.w_occ * losses["occ"]
        if cfg.w_unlabelled_uniform > 0:
            losses["unlabelled_uniform"] = unlabelled_uniform_loss(logits, _flat_semantics(batch, outputs), K, w)
            total = total + cfg.w_unlabelled_uniform * losses["unlabelled_uniform"]
    if not cfg.uses_grounding and cfg.use_occ:
        target = _flat_targets(batch, outputs, K)
        logits = class_logits(feat, bank.text, bank.phrase_class, K, free, None, free_bias=outputs.get("free_bias"))
        losses["occ"] = occupancy_loss(logits, target, K, weight=_occupancy_weight(w, batch, outputs, cfg),
                                       binary=_flat_occupancy(batch, outputs, K))
        total = total + cfg.w_occ * losses["occ"]
    if cfg.uses_align:
        if num_voxels is None:
            sem = batch["semantics"]
            num_voxels = sem.reshape(sem.shape[0], -1).shape[1]
        rows, emb = _align_rows(batch, outputs, num_voxels)
        if "align_center" in batch:
            emb = emb - batch["align_center"].to(emb.device, emb.dtype)
        if cfg.variant != "ago":
            src = feat.reshape(-1, feat.shape[-1])[rows]
        elif "feat_adapted" in outputs:
            src = outputs["feat_adapted"].reshape(-1, feat.shape[-1])[rows]
        elif adapter is not None:
            src = adapter(feat.reshape(-1, feat.shape[-1])[rows])
        else:
            raise ValueError("the 'ago' variant needs outputs['feat_adapted'] or an adapter")
        losses["align"] = align_loss(src, emb, cfg.align_loss,
                                     weight=None if w is None else w.reshape(-1)[rows])
        total = total + cfg.w_align * losses["align"]
    losses["total"] = total
    return losses
