"""Shared test fixtures: paths to the real reference data in ../shared (skipped when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("AGO_NO_PROGRESS", "1")

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
