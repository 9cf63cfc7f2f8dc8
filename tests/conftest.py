"""Shared test fixtures: paths to the real reference data in ../shared (skipped when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("AGO_NO_PROGRESS", "1")
if os.environ.get("PYTEST_XDIST_WORKER"):
    # `pytest -n 2` on 2 cores: each worker, and every torch process it starts, gets one OpenMP thread. Two
    # processes that each spin up an OpenMP thread per core starve each other (a 30 s training test took 240 s
    # beside the experiments fixture's training subprocess).
    os.environ.setdefault("OMP_NUM_THREADS", "1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test when the real data is not beside the repo."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real reference data not present ({p})")
    return p


@pytest.fixture
def nuscenes_sample_root() -> Path:
    return shared_path("nuscenes-sample")


@pytest.fixture
def occ3d_sample_labels() -> Path:
    root = shared_path("occ3d-nuscenes-sample", "gts")
    files = sorted(root.glob("*/*/labels.npz"))
    if not files:
        pytest.skip("no Occ3D labels.npz under ../shared")
    return files[0]


def ago_in_process(args) -> tuple[int, str]:
    """`ago ARGS` run in this process (ago_runtime.cli.run) -> (exit code, what it wrote to stderr)."""
    import contextlib
    import io

    from ago_runtime.cli import run

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = run([str(a) for a in args])
        except SystemExit as e:
            code = e.code
    return code, err.getvalue()


def tiny_town(out: Path, seed: int = 5) -> Path:
    """A 2-frame synthetic town at 192x128 with a 20x20x4 grid (`ago synth` in a subprocess of this tree): e.g. the
    calibration frames of an int8 export of a random checkpoint, which records no training data."""
    import os
    import subprocess
    import sys

    subprocess.run([sys.executable, "-m", "ago_runtime.cli", "synth", "--out", str(out), "--scenes", "1", "--frames",
                    "2", "--image-size", "192x128", "--grid", "20x20x4", "--seed", str(seed), "--val-fraction", "0"],
                   check=True, capture_output=True, env=dict(os.environ, AGO_NO_PROGRESS="1", PYTHONPATH=str(REPO)))
    return out
