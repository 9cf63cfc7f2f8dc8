"""DataLoader workers follow the machine: `num_workers` is capped at the cores the process may use
(ago_train.trainer.loader_workers), so the `full` preset's 4 workers raise no DataLoader warning on 2 cores."""

import os
import warnings

import pytest

torch = pytest.importorskip("torch")

from ago_train.train_config import TrainConfig  # noqa: E402
from ago_train.trainer import loader_workers  # noqa: E402


def _cores(monkeypatch, n: int) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(n)), raising=False)


def test_capped_at_the_cores(monkeypatch):
    _cores(monkeypatch, 2)
    assert loader_workers(4) == 2
    assert loader_workers(1) == 1
    assert loader_workers(0) == 0
    _cores(monkeypatch, 16)
    assert loader_workers(4) == 4


def test_without_affinity_the_cpu_count(monkeypatch):
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    assert loader_workers(8) == 3


def test_full_preset_on_two_cores_no_warning(monkeypatch):
    _cores(monkeypatch, 2)   # torch's own check reads the same affinity
    workers = loader_workers(TrainConfig.preset("full").num_workers)
    assert workers == 2
    loader = torch.utils.data.DataLoader(list(range(4)), batch_size=2, num_workers=workers)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sum(len(b) for b in loader) == 4
    # the uncapped 4 is what warned before
    with pytest.warns(UserWarning, match="worker"):
        list(torch.utils.data.DataLoader(list(range(4)), batch_size=2, num_workers=4))
