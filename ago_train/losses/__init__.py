"""AGO training losses: grounding (CE + Lovász-softmax), occupancy, alignment, and their total."""

from .total import BankTensors, LossConfig, compute_losses

__all__ = ["BankTensors", "LossConfig", "compute_losses"]
