"""Which prompt template should phrases be wrapped in? Measured on the closed-world label space.

For each template T ("{}" = the plain phrase) every phrase p of prompts/cw.txt whose text differs
from its class name is encoded as T(p), and every class name (underscores as spaces) as T(name).
  accuracy  share of those phrases whose nearest class name is their own class's;
  margin    mean over those phrases of cos(T(p), T(own name)) - max_other cos(T(p), T(other name));
  cross     mean over classes of the highest class-to-class similarity of the bank (max over
            phrase pairs; lower = classes easier to tell apart);
  ds        cos(T("road"), T("driveable surface")) - cos(T("tree"), T("driveable surface")).
  probe acc held-out synonyms (PROBES) classified through the bank as voxels are (max over phrases).
Winner: highest probe accuracy, ties broken by accuracy, then probe margin. Writes benchmarks/results/prompt_templates.md.

    python -m benchmarks.prompt_templates [--encoder torch|onnx|int8]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from ago_runtime.vocab.bank import apply_template, build_bank  # noqa: E402
from ago_runtime.vocab.prompts import name_key, parse_prompt_file  # noqa: E402

# Held-out probe words (in no prompt file) with the cw class they belong to: classified through the
# bank exactly as voxels are (class score = max over the class's phrases).
PROBES = {
    "barrier": ["guard rail", "crash barrier", "jersey barrier"],
    "bicycle": ["bike", "push bike", "racing bicycle"],
    "bus": ["coach", "school bus", "city bus"],
    "car": ["sedan", "automobile", "hatchback"],
    "construction_vehicle": ["excavator", "bulldozer", "crane truck"],
    "motorcycle": ["motorbike", "moped", "dirt bike"],
    "pedestrian": ["person walking", "woman", "man crossing the street"],
    "traffic_cone": ["pylon", "safety cone", "orange cone"],
    "trailer": ["semi-trailer", "caravan", "cargo trailer"],
    "truck": ["lorry", "pickup truck", "delivery truck"],
    "driveable_surface": ["asphalt", "street", "highway"],
    "other_flat": ["median strip", "canal", "railway"],
    "sidewalk": ["pavement", "footpath", "walkway"],
    "terrain": ["grass", "soil", "gravel"],
    "manmade": ["wall", "house", "bridge"],
    "vegetation": ["hedge", "shrubs", "plants"],
    "others": ["dog", "kick scooter", "pram"],
}

TEMPLATES = [
    "{}",
    "a {}.",
    "a photo of a {}.",
    "a {} in a street scene.",
    "a photo of a {} in a driving scene.",
    "there is a {} in the scene.",
    "a {} seen from a car.",
]


def get_encoder(kind: str):
    if kind == "torch":
        from ago_train.text.minilm import TorchMiniLMEncoder

        return TorchMiniLMEncoder()
    from ago_runtime.vocab.text_encoder import text_encoder_for

    return text_encoder_for(kind)


def evaluate(encoder, template: str) -> dict:
    space = parse_prompt_file("cw")
    names = [c.name.replace("_", " ") for c in space.classes]
    name_emb = encoder.encode([apply_template(template, n) for n in names])
    pairs = [(p, k) for k, c in enumerate(space.classes) for p in c.phrases if name_key(p) != name_key(c.name)]
    ph_emb = encoder.encode([apply_template(template, p) for p, _ in pairs])
    own = np.array([k for _, k in pairs])
    sim = ph_emb @ name_emb.T
    acc = float((sim.argmax(1) == own).mean())
    s_own = sim[np.arange(len(own)), own]
    sim_other = sim.copy()
    sim_other[np.arange(len(own)), own] = -np.inf
    margin = float((s_own - sim_other.max(1)).mean())
    cs = build_bank(space, encoder, template).class_similarity()
    np.fill_diagonal(cs, -np.inf)
    cross = float(cs.max(1).mean())
    bank = build_bank(space, encoder, template)
    probe = [(w, space.index(c)) for c, ws in PROBES.items() for w in ws]
    pe = encoder.encode([apply_template(template, w) for w, _ in probe])
    ps = bank.class_scores(pe @ bank.embeddings.T)
    plab = np.array([k for _, k in probe])
    probe_acc = float((ps.argmax(1) == plab).mean())
    p_own = ps[np.arange(len(plab)), plab]
    ps[np.arange(len(plab)), plab] = -np.inf
    probe_margin = float((p_own - ps.max(1)).mean())
    e = encoder.encode([apply_template(template, w) for w in ("road", "driveable surface", "tree")])
    ds = float(e[0] @ e[1] - e[2] @ e[1])
    return {"template": template, "n": len(pairs), "probe_acc": probe_acc, "probe_margin": probe_margin,
            "n_probe": len(probe), "accuracy": acc, "margin": margin, "cross": cross, "ds": ds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--encoder", default="torch", help="torch | onnx | int8 | PATH")
    ap.add_argument("-o", "--output", default=str(ROOT / "benchmarks/results/prompt_templates.md"))
    args = ap.parse_args()
    enc = get_encoder(args.encoder)
    t0 = time.time()
    rows = [evaluate(enc, t) for t in TEMPLATES]
    best = max(rows, key=lambda r: (r["probe_acc"], r["accuracy"], r["probe_margin"]))
    lines = [
        "# Prompt templates on the closed-world label space (prompts/cw.txt)",
        "",
        f"Command: `python -m benchmarks.prompt_templates --encoder {args.encoder}` "
        f"(encoder {enc.encoder_id}, {enc.variant}; {time.time() - t0:.1f} s).",
        "",
        f"probe acc / probe margin: {rows[0]['n_probe']} held-out words (3 per class, in no prompt file, listed in",
        "the script) classified through the cw bank like voxels (max over each class's phrases); margin =",
        "own-class score - best other class score (cosine).",
        f"accuracy / margin over the {rows[0]['n']} cw phrases that differ from their class name: is the",
        "phrase nearest to its own class name (T(phrase) vs T(class name))? cross: mean highest",
        "class-to-class similarity of the bank (lower is better). ds: cos(road, driveable surface) -",
        "cos(tree, driveable surface) (higher is better).",
        "",
        "| template | probe acc | probe margin | accuracy | margin | cross | ds |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mark = " **(winner)**" if r is best else ""
        lines.append(f"| `{r['template']}`{mark} | {r['probe_acc']:.3f} | {r['probe_margin']:+.3f} | {r['accuracy']:.3f} | {r['margin']:+.3f} | "
                     f"{r['cross']:.3f} | {r['ds']:+.3f} |")
    lines += ["", f"Winner (highest probe accuracy, then accuracy, then probe margin): `{best['template']}` -> "
              "ago_runtime.vocab.bank.DEFAULT_TEMPLATE.", ""]
    write_text(args.output, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
