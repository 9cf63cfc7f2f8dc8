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
