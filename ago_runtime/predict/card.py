"""The bundle card (`card.json`): what an exported model was trained on, as dataclasses.

`ago export` fills the card (ago_export/card.py `make_card`) and writes it through `write_card_file`;
`Bundle.load` reads it with `read_card` (`ago infer` and `ago demo` print its `summary`). Both go through
`BundleCard`, whose `from_dict` refuses a key the card does not declare, so what is written is what is read.
The layout is in docs/runtime.md ("Bundle card").
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, fields
from pathlib import Path

from ago_runtime.errors import AgoInputError
from ago_runtime.predict.contract import declared_keys, typed_value, record_from_dict, record_to_dict

CARD_FILE = "card.json"
CARD_FORMAT = "ago-bundle-card"
CARD_VERSION = 2


@dataclass
class CardData:
    """The training data folder (ago_export/card.py describe_data)."""

    kind: str                        # "synthetic" | "nuscenes" | "unknown"
    path: str | None = None
    split: str | None = None
    scenes: int | None = None
    frames: int | None = None
    image_size: list | None = None   # [width, height] of the camera images
    note: str | None = None          # e.g. "data folder not found at export time"


@dataclass
class CardPseudoLabels:
    path: str | None = None
    segmenter: str | None = None     # "simulated" | "files" | "boxes"
    embedder: str | None = None
    keyframes: int | None = None
    nonkey_sweeps: int | None = None


@dataclass
class CardLastLog:
    step: int | None = None
    loss: float | None = None
    total: float | None = None


@dataclass
class CardTraining:
    preset: str | None = None
    steps: int = 0
    epochs: int = 0
    batch_size: int | None = None
    init_from: str | None = None
    last_log: CardLastLog | None = None


@dataclass
class CardLabelSpace:
    name: str | None = None
    classes: list | None = None
    known: list | None = None


@dataclass
class CardScores:
    mIoU: float | None = None
    geometry_IoU: float | None = None
    split: str | None = None
    frames: int | None = None
    readout: str | None = None       # "model" | "gt" (`ago eval --readout`)
    source: str | None = None        # the metrics.json they come from


@dataclass
class CardTextEncoder:
    id: str
    variant: str | None = None
    dim: int | None = None
    kind: str | None = None          # "clip" for a CLIP folder's text tower (ago_export/text_tower.py)
    folder: str | None = None
    embedding: str | None = None
    hidden_size: int | None = None
    layers: int | None = None
    projection_dim: int | None = None
    max_length: int | None = None


@dataclass
class CardReadout:
    grid: list                       # the bundle's read-out grid shape
    model_grid: list                 # the model's training grid shape


@dataclass
class BundleCard:
    trained_on: CardData
    training: CardTraining
    label_space: CardLabelSpace
    summary: str
    pseudo_labels: CardPseudoLabels | None = None
    val_scores: CardScores | None = None
    text_encoder: CardTextEncoder | None = None
    readout: CardReadout | None = None
    note: str | None = None
    format: str = CARD_FORMAT
    version: int = CARD_VERSION

    # what `ago export --card-json FILE` may set (merged over the card before the summary is written)
    EXTRA_KEYS = ("trained_on", "training", "label_space", "pseudo_labels", "val_scores", "text_encoder", "readout",
                  "note")

    def to_dict(self) -> dict:
        return record_to_dict(self)

    @classmethod
    def from_dict(cls, d) -> "BundleCard":
        """card.json's content -> the card; ValueError for another format or version, a key the card does not
        declare, or a value of the wrong type."""
        card = record_from_dict(cls, d, "card")
        if (card.format, card.version) != (CARD_FORMAT, CARD_VERSION):
            raise ValueError(f"card format {card.format!r} version {card.version}, this ago reads {CARD_FORMAT!r} "
                             f"version {CARD_VERSION} (re-export the bundle)")
        return card

    @classmethod
    def check_extra(cls, extra: dict, source) -> None:
        """A `--card-json` object: only keys the card declares, each section's keys its own, values of their
        types; else AgoInputError(source, ...) (checked before the export runs)."""
        hints = typing.get_type_hints(cls)
        try:
            declared_keys(extra, cls.EXTRA_KEYS, "the card")
            for key, value in extra.items():
                kind = hints[key]
                record = [a for a in typing.get_args(kind) or (kind,) if hasattr(a, "__dataclass_fields__")]
                if record and isinstance(value, dict):   # merged over the section: its own keys, each of its type
                    sub = typing.get_type_hints(record[0])
                    declared_keys(value, [f.name for f in fields(record[0])], f"card.{key}")
                    for k, v in value.items():
                        typed_value(v, sub[k], f"card.{key}.{k}")
                else:
                    typed_value(value, kind, f"card.{key}")
        except ValueError as e:
            raise AgoInputError(source, str(e)) from None


def write_card_file(path: str | Path, card: dict) -> Path:
    """Write `card` (the card's JSON object) at `path` after reading it back as a BundleCard (a key the card does
    not declare is a bug of the writer: ValueError)."""
    from ago_runtime.atomic import write_json

    write_json(Path(path), BundleCard.from_dict(card).to_dict())
    return Path(path)


def read_card(path: str | Path) -> BundleCard:
    """card.json -> BundleCard; AgoInputError naming the file when it is not one."""
    from ago_runtime.readers import read_json

    try:
        return BundleCard.from_dict(read_json(path, expect=dict))
    except ValueError as e:
        raise AgoInputError(path, f"not a bundle card ({e})") from None
