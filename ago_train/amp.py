"""Mixed precision in training (`--set amp=bf16`): the model's forward under torch.autocast in bfloat16, the
losses in float32.

- `AMP_MODES`: "none" (float32 throughout, the default) or "bf16" (autocast to torch.bfloat16 on the device
  the batch is on, CPU or CUDA). bf16 keeps float32's exponent range, so no loss scaling is needed (unlike fp16).
- `forward_autocast(amp, device_type)`: the context the trainer runs the model's forward in.
- `outputs_to_float(outputs)`: the forward's floating tensors cast back to float32 before the losses (logits,
  softmaxes, log-sum-exps and the Lovasz sort run in float32; the adapter the alignment loss calls runs there too).
The parameters, their gradients and the optimiser state stay float32 (autocast casts per operation).
"""

from __future__ import annotations

import contextlib

AMP_MODES = ("none", "bf16")


def forward_autocast(amp: str, device_type: str):
    """torch.autocast(device_type, torch.bfloat16) for amp "bf16", else a context that does nothing."""
    import torch

    if amp == "bf16":
        return torch.autocast(device_type=device_type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def outputs_to_float(outputs: dict) -> dict:
    """The dict with every floating tensor in float32 (integer tensors and other values as they are)."""
    import torch

    return {k: (v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v) for k, v in outputs.items()}
