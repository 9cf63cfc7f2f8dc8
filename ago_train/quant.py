"""Quantisation-aware fine-tuning (`TrainConfig.quant = "int8"`): fake int8 on the convolutions, distilled from fp32.

What the int8 planes graph runs in int8 (ago_export.quantize.quantize_planes_static: the convolutions of the
image backbone and the FPN, uint8 activations with one range per tensor, int8 weights per output channel) is
what this module simulates in torch, on every nn.Conv2d of the model but the FPN's output convolutions
(`FLOAT_IN_INT8`: they make the features the TPV encoder samples, which the export keeps in float32,
ago_export.quantize.sampled_feature_convs; the TPV encoder's own value projections are functional convolutions,
not modules; the decoder and adapter are linear layers: their graphs stay float or dynamic int8):

- weights: symmetric int8 per output channel, scale = max |w| / 127 (`torch.fake_quantize_per_channel_affine`;
  a batch norm that follows the convolution scales whole output channels, so quantising the unfolded
  weight per channel equals quantising the folded one the ONNX graph holds);
- the convolution's input: asymmetric uint8 over a range [lo, hi] (0 always inside), an exponential moving
  average of each batch's min and max while training, fixed in eval mode (`ActivationFakeQuant`).

Both pass gradients straight through (inside the range). The weights stay float32 parameters under
`torch.nn.utils.parametrize`, so the optimiser and the checkpoint see the plain weights: `model_state`
gives the state dict with the plain parameter names (what every checkpoint reader expects) and
`load_model_state` loads one back into a model with fake quantisation attached.

The loss (`DistillStep`): the fine-tuned model with fake int8 learns to give the class distributions of the
fp32 model it starts from (the `init_from` checkpoint, kept frozen as the teacher): KL(teacher || student) of
softmax over [K classes + free], on the voxels of the usual voxel sample (weighted by the sample's importance
weights), for the main branch and the adapted branch. The goal is int8 labels that agree with the fp32 model's,
not a new model: the pseudo-label losses are not used, and the run keeps the teacher's calibration (the
identifier's branch scales, ago_train/calibrate.py) instead of fitting its own.

The export does not read the fake-quant ranges: `ago export --int8` calibrates the fine-tuned weights on
training frames (ago_export.quantize), the same recipe as post-training quantisation of the fp32 model.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils import parametrize

QUANT_MODES = ("none", "int8")
WEIGHT_QMAX = 127            # symmetric int8 weights: -127..127 (onnxruntime's symmetric QInt8 range)
ACT_QMAX = 255               # uint8 activations: 0..255
RANGE_MOMENTUM = 0.01        # the moving average of the activation ranges
_ORIGINAL = ".parametrizations.weight.original"


class WeightFakeQuant(nn.Module):
    """w (O, ...) -> w quantised to int8 per output channel (symmetric) and back, straight-through."""

    def forward(self, w: torch.Tensor) -> torch.Tensor:
        scale = w.detach().abs().flatten(1).amax(1).clamp_min(1e-8) / WEIGHT_QMAX
        zero = torch.zeros(w.shape[0], dtype=torch.int32, device=w.device)
        return torch.fake_quantize_per_channel_affine(w, scale.float(), zero, 0, -WEIGHT_QMAX, WEIGHT_QMAX)


class ActivationFakeQuant(nn.Module):
    """x -> x quantised to uint8 over the observed range [lo, hi] and back (see the module doc).
    The range is a non-persistent buffer: it is not part of any checkpoint."""

    def __init__(self):
        super().__init__()
        self.register_buffer("lo", torch.zeros(()), persistent=False)
        self.register_buffer("hi", torch.zeros(()), persistent=False)
        self.register_buffer("seen", torch.zeros((), dtype=torch.bool), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training or not bool(self.seen):
            with torch.no_grad():
                lo, hi = x.detach().min().clamp_max(0), x.detach().max().clamp_min(0)
                if bool(self.seen):
                    lo = self.lo + RANGE_MOMENTUM * (lo - self.lo)
                    hi = self.hi + RANGE_MOMENTUM * (hi - self.hi)
                self.lo.copy_(lo)
                self.hi.copy_(hi)
                self.seen.fill_(True)
        scale = float((self.hi - self.lo).clamp_min(1e-8)) / ACT_QMAX
        zero = int(min(max(round(-float(self.lo) / scale), 0), ACT_QMAX))
        return torch.fake_quantize_per_tensor_affine(x, scale, zero, 0, ACT_QMAX)


def _quantise_input(module: nn.Module, args: tuple) -> tuple:
    return (module.input_quant(args[0]), *args[1:])


# the modules whose convolutions the int8 planes graph keeps in float32 (the FPN outputs: the module doc)
FLOAT_IN_INT8 = ("fpn.output",)


def attach_fake_quant(model: nn.Module) -> int:
    """Fake int8 on every nn.Conv2d of `model` outside FLOAT_IN_INT8 (in place; see the module doc) -> how many
    convolutions."""
    convs = [m for name, m in model.named_modules() if isinstance(m, nn.Conv2d)
             and not any(name == f or name.startswith(f + ".") for f in FLOAT_IN_INT8)]
    for conv in convs:
        parametrize.register_parametrization(conv, "weight", WeightFakeQuant())
        conv.input_quant = ActivationFakeQuant().to(conv.weight.device)
        conv.register_forward_pre_hook(_quantise_input)
    return len(convs)


def model_state(model: nn.Module) -> dict[str, torch.Tensor]:
    """model.state_dict() under the plain parameter names (a fake-quantised weight's float32 original)."""
    return {k.replace(_ORIGINAL, ".weight"): v for k, v in model.state_dict().items()}


def load_model_state(model: nn.Module, state: dict[str, torch.Tensor]) -> None:
    """Load a plain state dict (model_state's names) into `model`, with or without fake quantisation attached."""
    own = model.state_dict()
    model.load_state_dict({(k[: -len(".weight")] + _ORIGINAL if k.endswith(".weight")
                            and k[: -len(".weight")] + _ORIGINAL in own else k): v for k, v in state.items()})


def distill_kl(student: torch.Tensor, teacher: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """KL(softmax(teacher) || softmax(student)) per voxel (last axis), averaged with `weight` (B, M) or evenly."""
    t = F.log_softmax(teacher.float(), -1)
    kl = (t.exp() * (t - F.log_softmax(student.float(), -1))).sum(-1)
    if weight is None:
        return kl.mean()
    w = weight.to(kl.dtype)
    return (kl * w).sum() / w.sum().clamp_min(1e-12)


class DistillStep(nn.Module):
    """The QAT step's loss (see the module doc): the student (fake int8) against the frozen fp32 teacher, on
    the same voxels; TrainStep's call signature, so the trainer runs either."""

    def __init__(self, model: nn.Module, teacher: nn.Module, num_classes: int):
        super().__init__()
        self.model = model
        self.teacher = teacher.eval()
        for p in self.teacher.parameters():
            p.requires_grad_(False)
        self.num_classes = int(num_classes)

    def train(self, mode: bool = True):
        super().train(mode)
        self.teacher.eval()
        return self

    def forward(self, batch: dict, text: torch.Tensor, phrase_class: torch.Tensor, noise, voxel_index=None,
                voxel_weight=None, class_weight=None, diagnose: bool = False) -> dict:
        from .model.text_logits import class_logits

        def logits(model, feat, out):
            return class_logits(feat, text, phrase_class, self.num_classes, out["free_embedding"],
                                free_bias=out.get("free_bias"))

        with torch.no_grad():
            t = self.teacher(batch["images"], batch["ego2img"], voxel_index, adapted=True)
            t_main, t_adapted = logits(self.teacher, t["feat"], t), logits(self.teacher, t["feat_adapted"], t)
        s = self.model(batch["images"], batch["ego2img"], voxel_index, adapted=True)
        main = distill_kl(logits(self.model, s["feat"], s), t_main, voxel_weight)
        adapted = distill_kl(logits(self.model, s["feat_adapted"], s), t_adapted, voxel_weight)
        with torch.no_grad():
            agree = (logits(self.model, s["feat"], s).argmax(-1) == t_main.argmax(-1)).float().mean()
        return {"total": main + adapted, "distill_main": main, "distill_adapted": adapted, "agree_main": agree}
