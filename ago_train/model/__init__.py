"""The AGO network (torch): config, backbone, FPN, TPV encoder, voxel heads, text scoring."""

from .config import ModelConfig

__all__ = ["ModelConfig"]
