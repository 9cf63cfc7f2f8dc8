"""The machine a timing ran on, for results files: the CPU model and its flags (lscpu), one reader for every
benchmark that records them."""

from __future__ import annotations

import subprocess


def cpu_model_and_flags() -> tuple[str, list[str]]:
    """(CPU model name, every flag lscpu lists); ("?", []) where lscpu is missing."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    except OSError:
        return "?", []
    fields = dict(ln.split(":", 1) for ln in text.splitlines() if ":" in ln)
    return fields.get("Model name", "?").strip(), fields.get("Flags", "").split()


SPEED_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8")   # what int8 / bf16 kernels use


def speed_flags(flags: list[str]) -> list[str]:
    """The SPEED_FLAGS among `flags` (cpu_model_and_flags), in that order: the line a timing's results file records."""
    return [f for f in SPEED_FLAGS if f in flags]
