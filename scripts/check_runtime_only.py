"""Check a runtime-only install (`bash scripts/setup.sh --runtime-only` in an environment WITHOUT torch):
a new prompt file becomes a bank and `ago infer` runs on the shipped demo frame with it, and torch is
never imported. Run with the environment's python: `VENV/bin/python scripts/check_runtime_only.py`.
Prints what it does; exits non-zero on the first failure. (.ci/run calls it after the main tests.)
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tempfile
from pathlib import Path

PROMPTS = """# a label space no shipped file has: encoded at run time by the int8 ONNX MiniLM
fire hydrant: fire hydrant, hydrant
road: road, street
building: building, house
tree: tree, bush
car: car, van
"""


def step(text: str) -> None:
    print(f"[runtime-only] {text}", flush=True)


def ago(*args: str, env: dict) -> subprocess.CompletedProcess:
    """`python -m ago_runtime ARGS` in this environment, with torch imports made to fail loudly."""
    r = subprocess.run([sys.executable, "-m", "ago_runtime", *args], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"FAILED: ago {' '.join(args)} (exit {r.returncode})\n{r.stdout}\n{r.stderr}")
    return r


def main() -> None:
    if importlib.util.find_spec("torch") is not None:
        raise SystemExit("FAILED: torch is importable here; run this in a runtime-only environment")
    step(f"python {sys.executable}: torch not installed")
    work = Path(tempfile.mkdtemp(prefix="ago-runtime-only-"))
    # an empty ago cache: no fp32 encoder exported by a full install may stand in for the packaged one
    env = dict(os.environ, AGO_CACHE_DIR=str(work / "cache"), AGO_NO_PROGRESS="1", PYTHONNOUSERSITE="1")
    env.pop("AGO_TEXT_ENCODER", None)
    prompt_file = work / "hydrants.txt"
    prompt_file.write_text(PROMPTS, encoding="utf-8")

    step("ago prompts build hydrants.txt -o bank.npz")
    r = ago("prompts", "build", str(prompt_file), "-o", str(work / "bank.npz"), env=env)
    print("  " + r.stdout.strip())

    step("ago infer --images <demo frame> --prompts hydrants.txt --html")
    r = ago("infer", "--images", str(Path(__file__).resolve().parents[1] / "ago_runtime" / "assets" / "demo_frame"),
            "--prompts", str(prompt_file), "--out", str(work / "out"), "--html", env=env)
    print("  " + " | ".join(ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip())[:400])

    import numpy as np

    npz = next((work / "out").glob("*.npz"))
    with np.load(npz, allow_pickle=False) as z:
        names = [str(n) for n in z["class_names"]]
        shape = z["semantics"].shape
    if "fire hydrant" not in names:
        raise SystemExit(f"FAILED: {npz} classes {names} lack the new prompt file's classes")
    step(f"{npz.name}: semantics {shape}, classes {names}")
    page = npz.with_suffix(".html")   # the 3-D page: its three.js bundle is package data of the install
    if not page.is_file() or "bundled by esbuild" not in page.read_text(encoding="utf-8"):
        raise SystemExit(f"FAILED: {page} missing or without the inlined three.js bundle")
    step(f"{page.name}: {page.stat().st_size} bytes")

    step("in-process: Predictor + bank from the prompt file, then check sys.modules")
    code = ("import sys; from ago_runtime.vocab.bank import load_prompt_bank; from ago_runtime.predict.predictor import Predictor; "
            "from ago_runtime.predict.bundle import resolve_bundle; from ago_runtime.formats.calibration import load_images_folder; "
            "from ago_runtime.predict.bundle import DEMO_FRAME_DIR; "
            f"bank = load_prompt_bank({str(prompt_file)!r}); p = Predictor(resolve_bundle()); "
            "imgs, rig, _ = load_images_folder(DEMO_FRAME_DIR); pred = p.predict(imgs, rig, bank); "
            "assert 'torch' not in sys.modules, 'torch was imported'; "
            "assert 'tokenizers' not in sys.modules, 'the MiniLM path loaded tokenizers'; "
            "print(pred.semantics.shape, bank.encoder_variant)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise SystemExit(f"FAILED: in-process prediction\n{r.stderr}")
    step(f"ok: {r.stdout.strip()}; torch (and tokenizers, a CLIP bundle's) never imported")


if __name__ == "__main__":
    main()
