"""CLI verb `ago synth`: write a procedural synthetic driving dataset in the nuScenes layout.

`ago synth --out data/synth --scenes N --frames M [--seed S] [--image-size 800x450] [--grid 200x200x16]
[--sweeps-between K]`
Needs numpy + opencv only (no torch). Deterministic given the seed.
"""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("synth")
    def synth(
        out: Path = typer.Option(Path("data/synth"), "--out", "-o", help="dataset root to write"),
        scenes: int = typer.Option(10, "--scenes", min=1, help="number of scenes"),
        frames: int = typer.Option(40, "--frames", min=1, help="keyframes per scene (2 Hz)"),
        seed: int = typer.Option(0, "--seed", min=0, help="random seed (same seed, same dataset)"),
        image_size: str = typer.Option("800x450", "--image-size", help="camera image WIDTHxHEIGHT"),
        grid: str = typer.Option("200x200x16", "--grid", help="Occ3D grid XxYxZ over [-40,40]x[-40,40]x[-1,5.4] m"),
        val_fraction: float = typer.Option(0.2, "--val-fraction", min=0.0, max=0.99,
                                           help="share of the scenes (the last ones) in val"),
        sweeps_between: int = typer.Option(0, "--sweeps-between", min=0, max=50,
                                           help="non-key LiDAR sweeps written between two keyframes, in "
                                                "sweeps/LIDAR_TOP like nuScenes (~9 there); 0 = keyframes only"),
        jobs: int = typer.Option(1, "--jobs", min=1, max=64,
                                 help="worker processes rendering scenes in parallel (same dataset for any value)"),
    ) -> None:
        """Generate a synthetic city: six cameras, a 32-beam LiDAR, 3D boxes and Occ3D ground truth."""
        from ago_runtime.outputs import check_output_dir

        from .config import SynthConfig, parse_size
        from .generate import write_dataset

        w, h = parse_size(image_size, 2, "--image-size")
        shape = parse_size(grid, 3, "--grid")
        check_output_dir(out, "--out")
        config = SynthConfig(seed=seed, num_scenes=scenes, frames_per_scene=frames, image_width=w, image_height=h,
                             grid_shape=shape, val_fraction=val_fraction, sweeps_between=sweeps_between)
        summary = write_dataset(config, out, jobs=jobs)
        typer.echo(f"wrote {summary['samples']} keyframes of {summary['scenes']} scenes "
                   f"({len(summary['splits']['train'])} train, {len(summary['splits']['val'])} val) to {out}")
