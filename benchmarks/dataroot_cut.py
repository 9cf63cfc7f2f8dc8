"""A train/val cut of a one-scene nuScenes dataroot, as a new dataroot (ago_runtime/formats/nuscenes_cut.py
says what is written; benchmarks/real_chain.py --cut uses it).

    python -m benchmarks.dataroot_cut SRC DST --train 22 --val 8
"""

from __future__ import annotations

import argparse

from ago_runtime.cli import exit_code_for
from ago_runtime.formats.nuscenes_cut import cut_dataroot

__all__ = ["cut_dataroot", "main"]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", help="a one-scene nuScenes dataroot")
    ap.add_argument("dst", help="the new dataroot (made; reused when it is the same cut)")
    ap.add_argument("--train", type=int, required=True, help="first TRAIN keyframes: split 'train'")
    ap.add_argument("--val", type=int, required=True, help="the next VAL keyframes: split 'val'")
    args = ap.parse_args(argv)
    try:
        rec = cut_dataroot(args.src, args.dst, args.train, args.val)
    except Exception as e:  # noqa: BLE001 - bad input: one `error:` line, exit 2 (others re-raised)
        raise SystemExit(exit_code_for(e)) from None
    print(f"{args.dst}: {rec['scene']} keyframes 0-{args.train - 1} = train, "
          f"{args.train}-{args.train + args.val - 1} = val")


if __name__ == "__main__":
    main()
