"""A bundle on a synthetic town it never saw, through the torch-free runtime (issue "The model must see").

    python -m benchmarks.fresh_town --town work/fresh101 [--bundle DIR] [--prompts prompts/cw.txt] \
        [--out benchmarks/results/default_bundle_fresh_town.md]

Make the town first with a seed no training used, e.g.
`ago synth --out work/fresh101 --scenes 2 --frames 16 --seed 101 --image-size 704x396 --grid 200x200x16 --val-fraction 0`.
Runs `ago infer --images TOWN` (every keyframe, `--picture none`) and `ago metric` as a user would
(subprocesses of this Python), then writes a markdown table with the command: per-class IoU with the
GT and predicted voxel counts, mIoU, geometry IoU, the occupancy ratio (predicted / GT occupied voxels
inside the camera mask, from the metric's confusion matrix) and the issue's targets.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

from ago_runtime.atomic import write_text  # noqa: E402
from benchmarks.learning_curve import occupancy_ratio  # noqa: E402

OBJECTS = ("car", "bus", "truck", "pedestrian", "barrier")


def run_ago(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "ago_runtime", *args], capture_output=True, text=True,
                       env={**__import__("os").environ, "AGO_NO_PROGRESS": "1"})
    if r.returncode != 0:
        raise SystemExit(f"ago {' '.join(args)} failed: {r.stderr.strip().splitlines()[-1:]}")
    return r.stdout


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--town", required=True, help="a dataset made by `ago synth` with an unused seed")
    ap.add_argument("--bundle", default=None, help="default: the shipped default bundle")
    ap.add_argument("--prompts", default=str(REPO / "prompts/cw.txt"))
    ap.add_argument("--out", default=str(REPO / "benchmarks/results/default_bundle_fresh_town.md"))
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ago-fresh-town-") as tmp:
        pred, js = Path(tmp) / "pred", Path(tmp) / "metric.json"
        infer = ["infer", "--images", args.town, "--prompts", args.prompts, "--out", str(pred), "--picture", "none"]
        if args.bundle:
            infer += ["--bundle", args.bundle]
        card = run_ago(*infer).splitlines()[0]
        run_ago("metric", "--pred", str(pred), "--gt", str(Path(args.town) / "gts"), "--json", str(js))
        m = json.loads(js.read_text())
    ratio = occupancy_ratio(m)
    names = m["class_names"]
    conf = m["confusion"]
    rows = []
    for i, c in enumerate(names):
        gt = sum(conf[i])
        pr = sum(r[i] for r in conf)
        iou = m["iou"].get(c)
        rows.append(f"| {c} | {'n/a' if iou is None else f'{iou:.2f}'} | {gt} | {pr} |")
    obj = {c: m["iou"].get(c) for c in OBJECTS if c in m["iou"]}
    zero = [c for c, v in obj.items() if v is not None and not v]   # None: absent from GT and prediction
    cmd = "python -m benchmarks.fresh_town " + " ".join(argv if argv is not None else sys.argv[1:])
    verdict = lambda ok: "met" if ok else "**missed**"   # noqa: E731
    text = f"""# A bundle on a town it never saw, through the torch-free runtime

Command: `{cmd}` (runs `ago infer --images {args.town} --prompts {Path(args.prompts).name} --picture none`
and `ago metric`; the town: `{args.town}`, {m['frames']} keyframes, Occ3D GT).

Bundle card: {card.removeprefix('bundle: ')}

| target (issue "The model must see") | value | |
|---|---:|---|
| mIoU >= 14 | {m['mIoU']:.2f} | {verdict(m['mIoU'] >= 14)} |
| geometry IoU >= 30 | {m['geometry_IoU']:.2f} | {verdict(m['geometry_IoU'] >= 30)} |
| occupancy ratio (predicted / GT occupied in the camera mask) within 0.5-2 | {ratio:.2f} | {verdict(0.5 <= ratio <= 2)} |
| object classes above 0 ({', '.join(OBJECTS)}) | {' / '.join('n/a' if v is None else f'{v:.2f}' for v in obj.values())} | {verdict(not zero)}{' (' + ', '.join(zero) + ' at 0)' if zero else ''} |

| class | IoU (%) | GT voxels | predicted voxels |
|---|---:|---:|---:|
{chr(10).join(rows)}
| **mIoU** | {m['mIoU']:.2f} | | |
| mIoU (1..16 / without first class) | {m['mIoU_1_16']:.2f} | | |
| mIoU* (without others, other_flat) | {m['mIoU_star']:.2f} | | |
| geometry IoU | {m['geometry_IoU']:.2f} | | |

{m['frames']} frame(s), {m['voxels']} voxels counted (camera mask); n/a = class absent from GT and predictions.
"""
    write_text(args.out, text)
    print(text)
    return {"mIoU": m["mIoU"], "geometry_IoU": m["geometry_IoU"], "occupancy_ratio": ratio, "objects": obj}


if __name__ == "__main__":
    main()
