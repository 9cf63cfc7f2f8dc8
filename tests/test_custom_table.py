"""Issue 38: a label table of one's own, given as a file, through the whole chain.

A synthetic nuScenes-layout town is relabelled into a coarse table of our own (sparse ids, free stored as 0) and
declares it with `<root>/class_table.json`; a prompt file names the table by a path relative to itself
(`@table: my_table.json`). Then `ago pseudo-labels` -> `ago train` -> `ago eval` -> `ago export` -> `ago infer` ->
`ago metric` run on it, and the table travels: the checkpoint records it, the bundle carries it, the prediction
files are in its dense order. Unit tests of the parts (prompt file, bank, bundle contract) come first."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ago_runtime.classes import OCC3D_NUSCENES, OCC3D_WAYMO, ClassTable, load_class_table
from ago_runtime.errors import AgoInputError
from test_bad_inputs import assert_one_error_line, ok, run_ago, run_chain

pytestmark = pytest.mark.xdist_group("test_custom_table")  # one worker builds the module fixtures (--dist loadgroup)

# our own table: file id of each class, and the Occ3D-nuScenes classes relabelled into it
MY_TABLE = {"name": "my_table", "free_id": 0, "ignore_ids": [255],
            "classes": [{"name": "vehicle", "id": 10}, {"name": "person", "id": 20},
                        {"name": "two_wheeler", "id": 21}, {"name": "ground", "id": 30},
                        {"name": "structure", "id": 40}, {"name": "vegetation", "id": 50, "color": [0, 175, 0]}]}
FROM_NUSCENES = {"vehicle": ("car", "truck", "bus", "trailer", "construction_vehicle"), "person": ("pedestrian",),
                 "two_wheeler": ("bicycle", "motorcycle"),
                 "ground": ("driveable_surface", "other_flat", "sidewalk", "terrain"),
                 "structure": ("manmade", "barrier", "traffic_cone", "others"), "vegetation": ("vegetation",)}
PROMPT_FILE = """@table: my_table.json
vehicle: car, truck, bus
person: pedestrian, person
two wheeler: bicycle, motorcycle
ground: road, sidewalk, grass
structure: building, wall, barrier
vegetation: tree, bushes
"""
NAMES = ["vehicle", "person", "two wheeler", "ground", "structure", "vegetation"]


def write_prompts(folder: Path, table: dict = MY_TABLE) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "my_table.json").write_text(json.dumps(table))
    (folder / "mine.txt").write_text(PROMPT_FILE)
    return folder / "mine.txt"


def nuscenes_to_mine() -> np.ndarray:
    """uint8 (256,): Occ3D-nuScenes label id -> our table's id (free 17 -> 0; 255 stays)."""
    lut = np.arange(256, dtype=np.uint8)
    for row in MY_TABLE["classes"]:
        for name in FROM_NUSCENES[row["name"]]:
            lut[OCC3D_NUSCENES.id_of(name)] = row["id"]
    lut[OCC3D_NUSCENES.free_id] = MY_TABLE["free_id"]
    return lut


def relabel(root: Path) -> None:
    """Rewrite an `ago synth` nuScenes-layout town's ground truth and per-pixel maps in our table, and declare it."""
    lut = nuscenes_to_mine()
    for f in (root / "gts").rglob("labels.npz"):
        with np.load(f) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["semantics"] = lut[arrays["semantics"]]
        np.savez_compressed(f, **arrays)
    for f in (root / "synthetic" / "semantic").rglob("*.png"):
        cv2.imwrite(str(f), lut[cv2.imread(str(f), cv2.IMREAD_UNCHANGED)])
    (root / "class_table.json").write_text(json.dumps(MY_TABLE))


# ---------------------------------------------------------------------------- the parts
def test_a_prompt_file_names_a_table_file_relative_to_itself(tmp_path):
    from ago_runtime.vocab.prompts import parse_prompt_file

    space = parse_prompt_file(write_prompts(tmp_path / "p"))
    assert space.class_table == load_class_table(tmp_path / "p" / "my_table.json") and space.table == "my_table"
    assert space.class_names == NAMES
    assert space.classes[space.index("two wheeler")].occ3d_ids == (21,)
    lut = space.gt_lut(space.num_classes)
    assert lut[0] == space.num_classes and lut[50] == space.index("vegetation") and lut[17] == 255
    # the same prompt text with another table file is another label space (its hash covers the table)
    other = dict(MY_TABLE, classes=[dict(c, id=c["id"] + 1) for c in MY_TABLE["classes"]])
    space2 = parse_prompt_file(write_prompts(tmp_path / "q", other))
    assert space2.sha256 != space.sha256 and space2.classes[0].occ3d_ids == (11,)


@pytest.mark.parametrize("table_line, files, needle", [
    ("@table: absent.json", {}, "line 1: @table: "),
    ("@table: t.json", {"t.json": "[1]"}, "expected a JSON dict"),
    ("@table: t.json", {"t.json": json.dumps(dict(MY_TABLE, name="occ3d_waymo"))}, "is a shipped table's"),
    ("@table: kitti", {}, "unknown class table 'kitti'"),
])
def test_a_bad_table_line_is_one_error_naming_the_prompt_file(tmp_path, table_line, files, needle):
    from ago_runtime.vocab.prompts import parse_prompt_file

    for name, text in files.items():
        (tmp_path / name).write_text(text)
    p = tmp_path / "bad.txt"
    p.write_text(f"{table_line}\nvehicle: car\n")
    with pytest.raises(AgoInputError) as e:
        parse_prompt_file(p)
    assert str(p) in str(e.value) and needle in str(e.value)


class _Enc:   # a stand-in text encoder: what the bank stores does not depend on the vectors
    encoder_id, variant, dim, weights_hash = "test", "test", 4, "0" * 64

    def encode(self, texts):
        v = np.random.default_rng(len(texts)).normal(size=(len(texts), 4)).astype(np.float32)
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_a_bank_carries_the_table_itself_and_the_cache_follows_the_table(tmp_path):
    from ago_runtime.predict.predictor import table_id_lookup
    from ago_runtime.vocab.bank import PromptBank, build_bank, load_prompt_bank
    from ago_runtime.vocab.prompts import parse_prompt_file

    prompts = write_prompts(tmp_path / "p")
    bank = build_bank(parse_prompt_file(prompts), _Enc())
    back = PromptBank.load(bank.save(tmp_path / "b.npz"))
    assert back.class_table == load_class_table(tmp_path / "p" / "my_table.json")
    assert json.loads(str(np.load(tmp_path / "b.npz")["meta"][0]))["class_table"]["classes"][0] == \
        {"name": "vehicle", "id": 10, "color": list(back.class_table.colors[0])}
    lut = table_id_lookup(back)   # bank class -> the table's dense order (free last)
    assert lut.tolist() == [0, 1, 2, 3, 4, 5, 6]
    # a cached bank of the same prompt text is not reused once the table file says other ids
    cache = tmp_path / "cache"
    first = load_prompt_bank(prompts, encoder=_Enc(), cache_dir=cache)
    other = dict(MY_TABLE, classes=[dict(c, id=c["id"] + 1) for c in MY_TABLE["classes"]])
    (tmp_path / "p" / "my_table.json").write_text(json.dumps(other))
    second = load_prompt_bank(prompts, encoder=_Enc(), cache_dir=cache)
    assert first.occ3d_ids[0] == (10,) and second.occ3d_ids[0] == (11,)
    # a bank whose ids its table does not name is refused
    back.occ3d_ids[0] = (99,)
    with pytest.raises(AgoInputError, match=r"occ3d_ids \[99\] are not ids of its class table my_table"):
        back._validate("b.npz")


def test_the_bundle_contract_records_a_custom_table_and_checks_ids_against_it():
    from ago_runtime.predict.contract import LabelClass, LabelSpaceSpec

    table = ClassTable.from_dict(MY_TABLE)
    spec = LabelSpaceSpec("mine", "0" * 64, [LabelClass("vehicle", [10], True, ["car"])], table)
    d = json.loads(json.dumps(spec.to_dict()))
    assert d["table"]["name"] == "my_table" and LabelSpaceSpec.from_dict(d).table == table
    waymo = LabelSpaceSpec("w", "0" * 64, [LabelClass("vehicle", [1], True, ["car"])], OCC3D_WAYMO).to_dict()
    assert waymo["table"] == "occ3d_waymo"
    assert LabelSpaceSpec("n", "0" * 64, [LabelClass("car", [4], True, ["car"])]).to_dict()["table"] == "occ3d_nuscenes"
    with pytest.raises(ValueError, match="outside class table my_table"):
        LabelSpaceSpec.from_dict(dict(d, classes=[{"name": "vehicle", "table_ids": [4], "known": True, "phrases": []}]))
    with pytest.raises(ValueError, match="not a shipped one"):
        LabelSpaceSpec.from_dict(dict(d, table="kitti"))


# ---------------------------------------------------------------------------- the chain
@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> Path:
    pytest.importorskip("torch")

    d = tmp_path_factory.mktemp("custom_table_chain")
    ok(run_ago(["synth", "--out", "s", "--scenes", "2", "--frames", "3", "--image-size", "192x108",
                "--grid", "40x40x4", "--seed", "7"], d))
    relabel(d / "s")
    run_chain(d, "s", write_prompts(d / "prompts"), gt="s/gts")
    return d


def test_the_dataset_takes_its_class_table_json(chain):
    from ago_runtime.formats.datasets import open_dataset

    ds = open_dataset(chain / "s", load_images=False, load_extras=False)
    assert ds.class_table == ClassTable.from_dict(MY_TABLE)
    values = set(np.unique(ds[0].gt.semantics).tolist())
    assert values <= {0, 10, 20, 21, 30, 40, 50, 255} and {0, 30}.issubset(values)


def test_the_checkpoint_and_the_bundle_carry_the_table(chain):
    import torch

    from ago_runtime.predict.bundle import Bundle
    from ago_train.checkpoint import LabelSpaceRecord

    ckpt = torch.load(chain / "run" / "last.pt", weights_only=True, map_location="cpu")
    assert ckpt["label_space"]["class_table"]["name"] == "my_table"
    (chain / "prompts" / "my_table.json").rename(chain / "prompts" / "moved.json")   # the record needs no file
    try:
        space = LabelSpaceRecord.from_payload(ckpt["label_space"], "last.pt").space
    finally:
        (chain / "prompts" / "moved.json").rename(chain / "prompts" / "my_table.json")
    assert space.class_table == ClassTable.from_dict(MY_TABLE) and space.class_names == NAMES
    b = Bundle.load(chain / "bundle")
    assert b.contract.label_space.table == ClassTable.from_dict(MY_TABLE)
    assert b.load_bank().class_table == ClassTable.from_dict(MY_TABLE)
    assert json.loads((chain / "bundle" / "bundle.json").read_text())["label_space"]["table"]["free_id"] == 0


def test_eval_infer_and_metric_score_in_the_table(chain):
    from ago_runtime.formats.datasets import open_dataset

    m = json.loads((chain / "ev" / "metrics.json").read_text())
    assert m["metric"]["class_names"] == NAMES + ["free"]
    ds = open_dataset(chain / "s", load_images=False, load_extras=False)
    val = [ds[i] for i in ds.split("val")]
    for name, file_id in (("ground", 30), ("free", 0)):
        gt = sum(int(((f.gt.semantics == file_id) & f.gt.mask_camera.astype(bool)).sum()) for f in val)
        assert gt > 0 and m["metric"]["counts"][name]["gt"] == gt
    with np.load(sorted((chain / "pred").rglob("*.npz"))[0]) as z:
        assert str(z["class_table"]) == "my_table"
        assert [str(c) for c in z["class_names"]] == [c["name"] for c in MY_TABLE["classes"]] + ["free"]
        assert int(z["free_index"]) == 6 and z["semantics"].max() <= 6
    s = json.loads((chain / "m.json").read_text())
    assert s["class_names"] == NAMES + ["free"] and s["frames"] == 6 and s["counts"]["free"]["gt"] > 0


def test_a_label_space_of_another_table_is_refused_naming_the_tables(chain):
    r = run_ago(["pseudo-labels", "--data", "s", "--prompts", "cw", "--out", "pl2", "--grid", "20x20x4"], chain)
    assert_one_error_line(r, "--prompts", "occ3d_nuscenes", "my_table", "class_table.json")
    assert not (chain / "pl2").exists()
    r = run_ago(["metric", "--pred", "pred", "--gt", "s/gts", "--prompts", "cw"], chain)
    assert_one_error_line(r, "holds my_table labels, not occ3d_nuscenes ones")


def test_show_draws_a_prediction_in_its_tables_colours(chain):
    from ago_runtime.pictures.cli import prediction_table

    pred = sorted((chain / "pred").rglob("*.npz"))[0]
    table = prediction_table(pred)
    mine = ClassTable.from_dict(MY_TABLE)
    assert table == mine.dense() and table.colors[5] == (0, 175, 0)   # vegetation's own colour, dense index 5
    r = run_ago(["show", pred, "--out", "shown.png"], chain)
    assert r.code == 0, r.stderr
    assert cv2.imread(str(chain / "shown.png")) is not None


def test_the_pseudo_label_folder_records_the_table(chain):
    from ago_train.pseudo.generate import PseudoLabelDir

    pl = PseudoLabelDir(chain / "pl")
    assert pl.meta["label_space"]["class_table"]["name"] == "my_table"
    space = pl.label_space()   # label_space.txt has no table file beside it: the meta's record serves
    assert not (chain / "pl" / "my_table.json").exists()
    assert space.class_table == ClassTable.from_dict(MY_TABLE) and space.class_names == NAMES
