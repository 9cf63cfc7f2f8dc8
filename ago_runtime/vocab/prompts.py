"""Prompt files and label spaces.

A prompt file (UTF-8 text, see docs/prompts.md) lists one class per line:

    # comment                       (from '#' to the end of the line)
    @name: cw                       (optional; default: the file name without .txt)
    @known: car, truck              (optional; the seen/known classes; default: all)
    @table: occ3d_waymo             (optional, before the classes; the class table names and [ids] are
                                     looked up in: occ3d_nuscenes (default), occ3d_waymo, or a class-table
                                     JSON file, its path relative to the prompt file: ago_runtime.classes)
    car: car, van, suv              (an Occ3D class name -> that Occ3D id)
    vehicle [car, bus, truck]: car, bus, lorry     (a class grouping several Occ3D classes)
    traffic sign: traffic sign      (no Occ3D name -> open vocabulary: predicted, not scored)
    curb []: curb, kerb             (explicitly open vocabulary)

`parse_prompt_file(path) -> LabelSpace`. Class order = line order = class index.
Every problem raises one AgoInputError naming the file and the line.
"""

from __future__ import annotations

import hashlib
import json
import re
import warnings
from functools import lru_cache
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ago_runtime.classes import (FREE, IGNORE, NUM_SEMANTIC, OCC3D_CLASSES, OCC3D_NUSCENES, SHIPPED_TABLES, ClassTable,
                                 load_class_table, name_key, shipped_name)
from ago_runtime.errors import AgoInputError, AgoNote

PROMPTS_DIR = Path(__file__).resolve().parents[2] / "prompts"
SHIPPED_FOLDERS = (Path("."), Path("waymo"))   # prompts/ and prompts/waymo/ (Occ3D-Waymo label spaces)
_CLASS_LINE = re.compile(r"^(?P<name>[^\[\]:@#]+?)\s*(?:\[(?P<ids>[^\]]*)\])?\s*:(?P<phrases>.*)$")
_NAME_OK = re.compile(r"^[\w][\w \-./']*$")


_OCC3D_KEY = {name_key(n): i for i, n in enumerate(OCC3D_CLASSES[:NUM_SEMANTIC])}


def _label(table) -> str:
    """How errors name a table's classes: "Occ3D" (Occ3D-nuScenes, the default) or the table's name."""
    return "Occ3D" if table.name == "occ3d_nuscenes" else table.name


def _table_id(table, name: str) -> int | None:
    """The label id of a class name in `table` (a ClassTable), else None."""
    try:
        return table.id_of(name)
    except KeyError:
        return None


def _table_of(value: str, source, where, at: str) -> ClassTable:
    """The class table an `@table:` line names: a shipped table (occ3d_nuscenes, occ3d_waymo) or a class-table JSON
    file, a relative path taken from the prompt file's folder; one AgoInputError naming the prompt file and line."""
    if value in SHIPPED_TABLES:
        return SHIPPED_TABLES[value]
    if not value.lower().endswith(".json"):
        raise AgoInputError(where, f"{at}: unknown class table {value!r} (one of {', '.join(SHIPPED_TABLES)}, "
                            "or a class-table .json file)")
    folder = Path(source).parent if source is not None else None
    try:
        return load_class_table(value, relative_to=folder)
    except AgoInputError as e:
        raise AgoInputError(where, f"{at}: @table: {e}") from None


def occ3d_id(name: str) -> int | None:
    """Occ3D id (0..16) of a class name ("driveable surface" == "driveable_surface"), else None."""
    return _OCC3D_KEY.get(name_key(name))


@dataclass(frozen=True)
class PromptClass:
    name: str
    phrases: tuple[str, ...]
    occ3d_ids: tuple[int, ...] = ()   # label ids in the space's class table (Occ3D-nuScenes by default);
                                      # empty: open vocabulary (predicted, not scored)

    @property
    def open_vocabulary(self) -> bool:
        return not self.occ3d_ids


@dataclass
class LabelSpace:
    """The classes a model predicts, their prompt phrases and their Occ3D ids."""

    name: str
    classes: list[PromptClass]
    known: set[str] = field(default_factory=set)   # names of seen classes; empty set allowed
    source: Path | None = None
    sha256: str = ""
    class_table: ClassTable = OCC3D_NUSCENES   # the class table `occ3d_ids` index (@table; ago_runtime.classes)

    @property
    def table(self) -> str:
        """The class table's name (messages; `class_table` is the table itself)."""
        return self.class_table.name

    @property
    def class_names(self) -> list[str]:
        return [c.name for c in self.classes]

    @property
    def num_classes(self) -> int:
        return len(self.classes)

    @property
    def phrases(self) -> list[str]:
        """All phrases, class by class (class 0's phrases first)."""
        return [p for c in self.classes for p in c.phrases]

    @property
    def phrase_class(self) -> np.ndarray:
        """int64 (num_phrases,): the class index of each phrase of `phrases`."""
        return np.array([k for k, c in enumerate(self.classes) for _ in c.phrases], dtype=np.int64)

    def known_mask(self) -> np.ndarray:
        """bool (num_classes,): True for known (seen) classes."""
        return np.array([c.name in self.known for c in self.classes], dtype=bool)

    def index(self, name: str) -> int:
        keys = [name_key(n) for n in self.class_names]
        try:
            return keys.index(name_key(name))
        except ValueError:
            raise KeyError(f"no class {name!r} in label space {self.name!r}") from None

    def gt_lut(self, free_index: int = FREE) -> np.ndarray:
        """uint8 (256,): Occ3D id -> class index in this space.

        Occ3D free (17) -> `free_index` (default 17, the Occ3D FREE marker; pass num_classes when
        the space has more than 17 classes); Occ3D classes this space doesn't cover -> 255 (IGNORE);
        255 stays 255.
        """
        if free_index < self.num_classes or free_index > 254:
            raise ValueError(f"free_index {free_index} collides with class indices 0..{self.num_classes - 1}")
        lut = np.full(256, IGNORE, dtype=np.uint8)
        for k, c in enumerate(self.classes):
            lut[list(c.occ3d_ids)] = k
        lut[self.class_table.free_id] = free_index   # the table's free label (Occ3D-nuScenes 17, -Waymo 23)
        return lut

    def check_consistency(self) -> None:
        """Raise AgoInputError unless each Occ3D class maps to at most one class and names are unique."""
        seen: dict[int, str] = {}
        for c in self.classes:
            for i in c.occ3d_ids:
                if i in seen and seen[i] != c.name:
                    raise AgoInputError(self.source, f"{_label(self.class_table)} class {self.class_table.name_of(i)!r} is in two classes: "
                                        f"{seen[i]!r} and {c.name!r}")
                seen[i] = c.name
        keys = [name_key(n) for n in self.class_names]
        if len(set(keys)) != len(keys):
            raise AgoInputError(self.source, "duplicate class names")
        unknown = set(self.known) - set(self.class_names)
        if unknown:
            raise AgoInputError(self.source, f"known classes not in the space: {sorted(unknown)}")


def _split_list(text: str) -> list[str]:
    return [" ".join(p.split()) for p in text.split(",") if p.strip()]


# Bounds on what a prompt file (or a --phrase) may ask the text encoder to do, checked before any encoding.
MAX_PROMPT_BYTES = 1 << 20      # a prompt file of more than 1 MiB is refused (the shipped ones are < 4 kB)
MAX_PHRASE_CHARS = 300          # the text encoder reads 256 word pieces; a phrase is a few words
MAX_PHRASES = 20000             # phrases in one file


def check_phrase(phrase: str, where, what: str = "phrase") -> str:
    """`phrase` with its white space folded, or AgoInputError naming `where`: empty, longer than
    MAX_PHRASE_CHARS, or holding a control character (a NUL, an escape, a tab inside a phrase...)."""
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in phrase):
        bad = next(c for c in phrase if ord(c) < 32 or 127 <= ord(c) < 160)
        raise AgoInputError(where, f"{what} holds the control character {bad!r}")
    if len(phrase) > MAX_PHRASE_CHARS:
        raise AgoInputError(where, f"{what} is {len(phrase)} characters long (at most {MAX_PHRASE_CHARS}: "
                                   "a phrase is a few words)")
    phrase = " ".join(phrase.split())
    if not phrase:
        raise AgoInputError(where, f"{what} is empty")
    return phrase


def _truncate_long_phrase(phrase: str, where: str, max_tokens: int) -> str:
    """`phrase`, cut at a word boundary to at most `max_tokens` word pieces (with a warning). A word piece
    holds at least one character that is not white space, so a phrase with no more such characters than
    `max_tokens` is never cut and the tokenizer is not loaded for it (the usual case: phrases are a few
    words, the limit 254)."""
    if sum(not c.isspace() for c in phrase) <= max_tokens:
        return phrase
    tok = _default_tokenizer()
    if tok is None or len(tok.tokenize_ids(phrase)) <= max_tokens:
        return phrase
    words = phrase.split()
    while len(words) > 1 and len(tok.tokenize_ids(" ".join(words))) > max_tokens:
        words.pop()
    short = " ".join(words)
    warnings.warn(f"{where}: phrase longer than the text encoder's {max_tokens} word pieces, "
                  f"truncated to {short[:60]!r}...", stacklevel=4)
    return short


@lru_cache(maxsize=1)
def _default_tokenizer():
    """The installed MiniLM's WordPiece tokenizer, or None without it."""
    from ago_runtime.vocab.text_encoder import minilm_max_length, minilm_vocab_path
    from ago_runtime.vocab.tokenizer import WordPieceTokenizer

    vocab = minilm_vocab_path()
    return WordPieceTokenizer(vocab, max_length=minilm_max_length()) if vocab is not None else None


@lru_cache(maxsize=1)
def _default_max_tokens() -> int:
    """Word pieces a phrase may have: the installed MiniLM's max_seq_length - 2 ([CLS] and [SEP])."""
    from ago_runtime.vocab.text_encoder import minilm_max_length

    return minilm_max_length() - 2


def parse_prompt_text(text: str | bytes, name: str | None = None, source: str | Path | None = None,
                      max_tokens: int | None = None, table: ClassTable | None = None) -> LabelSpace:
    """Parse prompt-file content (see the module docstring). `source` names it in errors. `table`: the class table
    its `@table:` line stands for, as recorded beside the text (a checkpoint's: `ago_train.checkpoint.LabelSpaceRecord`), used
    instead of reading the table file again."""
    recorded = table
    where = str(source) if source is not None else "<prompt text>"
    raw = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if len(raw) > MAX_PROMPT_BYTES:
        raise AgoInputError(where, f"prompt file of {len(raw)} bytes (at most {MAX_PROMPT_BYTES})")
    if b"\x00" in raw:
        line = raw[: raw.index(b"\x00")].count(b"\n") + 1
        raise AgoInputError(where, f"line {line}: holds a NUL byte")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise AgoInputError(where, f"line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x})") from None
    if text.startswith("\ufeff"):
        text = text[1:]
    classes: list[PromptClass] = []
    class_line: dict[str, int] = {}
    phrase_owner: dict[str, tuple[str, int]] = {}
    occ3d_owner: dict[int, tuple[str, int]] = {}
    known: set[str] | None = None
    known_line = 0
    space_name = name
    table = OCC3D_NUSCENES
    table_line = False
    table_text = b""   # a table file's bytes: part of the label space's hash
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        at = f"line {lineno}"
        if line.startswith("@"):
            key, sep, value = line[1:].partition(":")
            key = key.strip().lower()
            if not sep:
                raise AgoInputError(where, f"{at}: directive needs a colon, e.g. '@known: car, truck'")
            if key == "known":
                if known is not None:
                    raise AgoInputError(where, f"{at}: second @known line (first on line {known_line})")
                known, known_line = set(_split_list(value)), lineno
            elif key == "name":
                space_name = space_name or value.strip()
            elif key == "table":
                if classes:
                    raise AgoInputError(where, f"{at}: @table must come before the first class line")
                table = recorded if recorded is not None else _table_of(value.strip(), source, where, at)
                table_line = True
                if shipped_name(table) is None:
                    table_text = json.dumps(table.to_dict(), sort_keys=True).encode("utf-8")
            else:
                raise AgoInputError(where, f"{at}: unknown directive @{key} (known: @name, @known, @table)")
            continue
        m = _CLASS_LINE.match(line)
        if m is None:
            raise AgoInputError(where, f"{at}: expected 'class name: phrase, phrase, ...', got {line[:60]!r}")
        cname = " ".join(m.group("name").split())
        if not _NAME_OK.match(cname):
            raise AgoInputError(where, f"{at}: bad class name {cname!r}")
        if name_key(cname) in class_line:
            raise AgoInputError(where, f"{at}: duplicate class {cname!r} (first on line "
                                f"{class_line[name_key(cname)]})")
        class_line[name_key(cname)] = lineno
        if m.group("ids") is not None:
            ids = []
            for occ in _split_list(m.group("ids")):
                i = _table_id(table, occ)
                if i is None:
                    raise AgoInputError(where, f"{at}: {occ!r} is not an {_label(table)} class name "
                                        f"(one of {', '.join(table.names)})")
                if i not in ids:
                    ids.append(i)
            occ_ids = tuple(ids)
        else:
            i = _table_id(table, cname)
            occ_ids = () if i is None else (i,)
        for i in occ_ids:
            if i in occ3d_owner:
                other, other_line = occ3d_owner[i]
                raise AgoInputError(where, f"{at}: {_label(table)} class {table.name_of(i)!r} is already in class "
                                    f"{other!r} (line {other_line})")
            occ3d_owner[i] = (cname, lineno)
        phrases: list[str] = []
        for p in _split_list(m.group("phrases")):
            p = check_phrase(p, where, f"line {lineno}: phrase")
            if len(phrase_owner) >= MAX_PHRASES:
                raise AgoInputError(where, f"{at}: more than {MAX_PHRASES} phrases")
            limit = max_tokens if max_tokens is not None else _default_max_tokens()
            p = _truncate_long_phrase(p, f"{where}:{lineno}", limit)
            pk = p.lower()
            if pk in phrase_owner:
                other, other_line = phrase_owner[pk]
                if other == cname:
                    warnings.warn(f"{where}:{lineno}: phrase {p!r} repeated in class {cname!r}; kept once",
                                  stacklevel=3)
                    continue
                raise AgoInputError(where, f"{at}: phrase {p!r} is also in class {other!r} (line {other_line})")
            phrase_owner[pk] = (cname, lineno)
            phrases.append(p)
        if not phrases:
            raise AgoInputError(where, f"{at}: class {cname!r} has no phrases")
        classes.append(PromptClass(cname, tuple(phrases), occ_ids))
    if not classes:
        raise AgoInputError(where, "no classes (the file is empty or only comments)")
    if recorded is not None and not table_line and recorded != table:
        raise AgoInputError(where, f"the recorded class table is {recorded.name} but the prompt text has no @table line")
    names = {name_key(c.name): c.name for c in classes}
    if known is None:
        known_names = {c.name for c in classes}
    else:
        missing = [k for k in known if name_key(k) not in names]
        if missing:
            raise AgoInputError(where, f"line {known_line}: @known names classes not in the file: {missing}")
        known_names = {names[name_key(k)] for k in known}
    if space_name is None:
        space_name = Path(source).stem if source is not None else "prompts"
    space = LabelSpace(space_name, classes, known_names, Path(source) if source is not None else None,
                       hashlib.sha256(raw + table_text).hexdigest(), table)
    space.check_consistency()
    return space


def resolve_prompt_file(name_or_path: str | Path, option: str | None = None) -> Path:
    """The one prompt-file lookup: `name_or_path` when that file exists; else a shipped prompt file, for a
    bare name ("ow", "ow.txt") or the shipped folder's own spelling ("prompts/ow.txt", as the README writes
    it, from any working folder), with an AgoNote naming the file taken. Anything else is refused, naming
    `option` (e.g. "--prompts") when given: a path in another folder never falls back to a shipped file."""
    value = str(name_or_path)
    where = option or value
    p = Path(value)
    if p.is_file():
        return p
    if p.exists():
        raise AgoInputError(where, f"{value} is a folder, not a prompt file")
    shipped = ", ".join(shipped_label_spaces())
    folder = Path(*p.parent.parts[1:]) if p.parent.parts[:1] == ("prompts",) else p.parent
    if folder not in SHIPPED_FOLDERS or p.suffix not in ("", ".txt"):
        raise AgoInputError(where, f"{value}: prompt file not found (a shipped one is named without a folder, "
                                   f"e.g. ow, or waymo/<name>; shipped: {shipped})")
    candidate = PROMPTS_DIR / folder / (p.name if p.suffix == ".txt" else f"{p.name}.txt")
    if not candidate.is_file():
        raise AgoInputError(where, f"{value}: prompt file not found, nor a shipped label space of that name "
                                   f"(shipped: {shipped})")
    # a shipped name ("cw", "waymo/cw_waymo", a preset's default) names a shipped file; a path-like value that is not
    # here ("cw.txt", "prompts/ow.txt") is worth saying
    why = "" if p.suffix == "" and p.parent.parts[:1] != ("prompts",) else "no such file here; "
    warnings.warn(f"{option + ' ' if option else ''}{value}: {why}using the shipped {candidate}", AgoNote, stacklevel=3)
    return candidate


def parse_prompt_file(path: str | Path, max_tokens: int | None = None, option: str | None = None) -> LabelSpace:
    """Read and check a prompt file (or a shipped one by name, e.g. "cw": `resolve_prompt_file`, whose
    errors name `option`); see the module docstring.

    Phrases longer than the text encoder's limit (`max_tokens` word pieces; default the installed
    MiniLM's max_seq_length - 2) are cut at a word boundary with a warning.
    """
    path = resolve_prompt_file(path, option)
    try:
        if path.stat().st_size > MAX_PROMPT_BYTES:
            raise AgoInputError(path, f"prompt file of {path.stat().st_size} bytes (at most {MAX_PROMPT_BYTES})")
        raw = path.read_bytes()
    except OSError as e:
        raise AgoInputError(path, f"cannot read: {e.strerror}") from None
    return parse_prompt_text(raw, source=path, max_tokens=max_tokens)


def shipped_label_spaces() -> list[str]:
    """Names of the prompt files shipped in prompts/ (cw, ow, ow_pretrain, veon_...; the Occ3D-Waymo ones in
    prompts/waymo/ are found as waymo/<name> but not listed here: export ships a bank for each listed one)."""
    return sorted(q.stem for q in PROMPTS_DIR.glob("*.txt"))
