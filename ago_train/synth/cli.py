"""CLI verb `ago synth`: write a procedural synthetic driving dataset in the nuScenes layout.

`ago synth --out data/synth --scenes N --frames M [--seed S] [--rig nuscenes|waymo|front]
[--layout nuscenes|occ3d-waymo] [--image-size 800x450] [--grid 200x200x16] [--sweeps-between K]`
--rig nuscenes (default): six cameras, nuScenes layout. --rig waymo: Waymo's five cameras (two image
heights), --rig front: its front camera alone; both write the Occ3D-Waymo layout unless
`--layout nuscenes` asks for the nuScenes layout (synth/rigs.py).
Needs numpy + opencv only (no torch). Deterministic given the seed.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from .rigs import LAYOUTS, RIGS

# the choices of --rig and --layout, as Enums so that typer derives their help and their check (synth/rigs.py)
SynthRig = Enum("SynthRig", {name: name for name in RIGS}, type=str)
SynthLayout = Enum("SynthLayout", {name: name for name in LAYOUTS}, type=str)


# Bounds on what one `ago synth` may be asked to make, checked before any work (tests/test_bad_inputs.py).
MAX_SCENES = 10000
MAX_FRAMES = 100          # 50 s at 2 Hz (a nuScenes scene is 20 s); the city is sized by the ego's travel
MAX_IMAGE_SIDE = 4096
MAX_GRID_XY, MAX_GRID_Z = 800, 64


def register(app: typer.Typer) -> None:
    @app.command("synth")
    def synth(
        out: Path = typer.Option(Path("data/synth"), "--out", "-o", help="dataset root to write"),
        scenes: int = typer.Option(10, "--scenes", min=1, max=MAX_SCENES, help="number of scenes"),
        frames: int = typer.Option(40, "--frames", min=1, max=MAX_FRAMES,
                                   help="keyframes per scene (2 Hz; the city grows with the scene's length)"),
        seed: int = typer.Option(0, "--seed", min=0, help="random seed (same seed, same dataset)"),
        rig: SynthRig = typer.Option(SynthRig("nuscenes"), "--rig",
                                     help="cameras: nuscenes (six, nuScenes layout), waymo (five, Occ3D-Waymo layout) "
                                          "or front (Waymo's front camera alone, Occ3D-Waymo layout)"),
        layout: Optional[SynthLayout] = typer.Option(None, "--layout",
                                                     help="dataset layout (default: the rig's own; --layout "
                                                          "nuscenes writes any rig with Occ3D-nuScenes labels)"),
        image_size: str = typer.Option(None, "--image-size",
                                       help="camera image WIDTHxHEIGHT (default 800x450; waymo/front: 960x640, "
                                            "the side cameras as wide and 886/1280 as tall)"),
        grid: str = typer.Option("200x200x16", "--grid", help="Occ3D grid XxYxZ over [-40,40]x[-40,40]x[-1,5.4] m"),
        val_fraction: float = typer.Option(0.2, "--val-fraction", min=0.0, max=0.99,
                                           help="share of the scenes (the last ones) in val"),
        sweeps_between: int = typer.Option(0, "--sweeps-between", min=0, max=50,
                                           help="non-key LiDAR sweeps written between two keyframes, in "
                                                "sweeps/LIDAR_TOP like nuScenes (~9 there); 0 = keyframes only"),
        jobs: int = typer.Option(1, "--jobs", min=1, max=64,
                                 help="worker processes rendering scenes in parallel (same dataset for any value)"),
    ) -> None:
        """Generate a synthetic city: a camera rig, a 32-beam LiDAR, 3D boxes and Occ3D ground truth."""
        from ago_runtime.errors import AgoInputError
        from ago_runtime.outputs import check_output_dir

        from ..model.config import check_min_grid
        from .config import SynthConfig, parse_size
        from .generate import write_dataset
        from .rigs import DEFAULT_IMAGE_SIZE, LAYOUT_OF_RIG

        rig, layout = rig.value, layout.value if layout is not None else None
        if (layout or LAYOUT_OF_RIG[rig]) == "occ3d-waymo" and sweeps_between:
            raise AgoInputError("--sweeps-between", "the Occ3D-Waymo layout has no LiDAR sweeps")
        w, h = parse_size(image_size, 2, "--image-size") if image_size is not None else DEFAULT_IMAGE_SIZE[rig]
        shape = parse_size(grid, 3, "--grid")
        if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE:
            raise AgoInputError("--image-size", f"{w}x{h}: each side at most {MAX_IMAGE_SIDE} pixels")
        if max(shape[:2]) > MAX_GRID_XY or shape[2] > MAX_GRID_Z:
            raise AgoInputError("--grid", f"{'x'.join(map(str, shape))}: at most {MAX_GRID_XY}x{MAX_GRID_XY}x{MAX_GRID_Z} "
                                          "voxels (Occ3D: 200x200x16)")
        check_min_grid(shape, "--grid")
        check_output_dir(out, "--out")
        config = SynthConfig(seed=seed, num_scenes=scenes, frames_per_scene=frames, image_width=w, image_height=h,
                             grid_shape=shape, val_fraction=val_fraction, sweeps_between=sweeps_between,
                             rig_name=rig, layout=layout or "")
        summary = write_dataset(config, out, jobs=jobs)
        typer.echo(f"wrote {summary['samples']} keyframes of {summary['scenes']} scenes "
                   f"({len(summary['splits']['train'])} train, {len(summary['splits']['val'])} val) to {out}")
