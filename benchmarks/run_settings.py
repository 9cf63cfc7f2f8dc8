"""What a benchmark's training run was trained with, and the refusal to reuse a run trained otherwise.

- `asked_config(preset, sets)`: the `TrainConfig` that `ago train --config PRESET --set K=V ...` builds (the
  `--data/--pseudo/--out` options are the same `--set`s).
- `check_reuse(run, asked)`: before a benchmark reuses a run folder (its last.pt, its snapshots/step_N.pt),
  the run's recorded config.json must equal the asked one; else one line `error: <run>/config.json: ...`
  naming the settings that differ, and exit 2. A folder without config.json has nothing to reuse.
- `trained_settings(run, preset)`: the run's recorded settings that differ from the preset, `key=value`,
  for the results file ("trained with").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _get(d: dict, dotted: str):
    """A nested dict's value at a dotted key (None when absent), as JSON text."""
    for part in dotted.split("."):
        d = d.get(part) if isinstance(d, dict) else None
    return json.dumps(d)


def asked_config(preset: str, sets: list[str]):
    from ago_train.train_config import TrainConfig

    return TrainConfig.from_name_or_path(preset).with_overrides(sets)


def check_reuse(run: Path, asked) -> None:
    from ago_train.checkpoint import config_differences
    from ago_train.train_config import TrainConfig

    path = Path(run) / "config.json"
    if not path.is_file():
        return
    recorded = TrainConfig.load(path)
    diff = config_differences(recorded.to_dict(), asked.to_dict())
    if diff:
        rec, ask = recorded.to_dict(), asked.to_dict()
        shown = ", ".join(f"{k} was {_get(rec, k)}, asked {_get(ask, k)}" for k in diff[:4])
        more = f" (+{len(diff) - 4} more)" if len(diff) > 4 else ""
        print(f"error: {path}: the run there trained with other settings than asked ({shown}{more}); "
              "give another --work folder or remove that run", file=sys.stderr)
        raise SystemExit(2)


def trained_settings(run: Path, preset: str) -> list[str]:
    """`key=value` (JSON values) of the run's config.json that differ from the preset's."""
    from ago_train.checkpoint import config_differences
    from ago_train.train_config import TrainConfig

    rec = TrainConfig.load(Path(run) / "config.json").to_dict()
    base = TrainConfig.from_name_or_path(preset).to_dict()
    return [f"{key}={_get(rec, key)}" for key in config_differences(base, rec)]
