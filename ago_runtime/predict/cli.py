"""`ago infer`, `ago demo`, `ago retrieve`: run an exported bundle on camera images (no torch).

Inputs (`--images DIR`):
- an images folder: the six images named by camera (`CAM_FRONT.jpg` ...) and a `calib.json`
  (docs/runtime.md; without it the bundle's training rig is used, with a warning);
- a nuScenes-layout dataset (a `v1.0-*` table folder): every keyframe, or `--sample TOKEN|SCENE`
  (repeatable: several tokens and/or scene names in one run, the bundle loaded once);
- with `--info PKL`: an mmdetection3d info file, DIR (default: the pkl's folder) the data root.

Outputs per frame, in `--out` (all written atomically): `<name>.npz` (Occ3D format: `semantics`
uint8 with free = 17 when every class is one Occ3D class, else bank class indices with free = K;
`class_names`, `free_index`; with --save-volumes also `entropy`, `confidence`, `branch` and the
unexplained-obstacle volumes `unexplained` (score), `unexplained_mask`, `unexplained_threshold`) and
`<name>.png` (--picture full: BEV of the classes, entropy BEV, camera mosaic, legend; bev: the class
BEV and legend; none: no PNG). Reading, inference and writing overlap (run_infer).
"""

from __future__ import annotations

import collections
import os
import queue
import threading
import time
from pathlib import Path
from typing import Iterator, List, Optional

import numpy as np
import typer

from ago_runtime.errors import AgoInputError, one_line_warnings


def resolve_prompts(path: str) -> Path:
    """A prompt file relative to the cwd, else in the installed `prompts` package (by name or file name)."""
    from ago_runtime.vocab.prompts import PROMPTS_DIR, resolve_prompt_file

    p = Path(path)
    if p.is_file():
        return p
    if (PROMPTS_DIR / p.name).is_file():
        return PROMPTS_DIR / p.name
    return resolve_prompt_file(path)   # shipped name ("ow") or a clear error


def choose_bank(bundle, prompts: Optional[str], bank: Optional[str]):
    """The bank infer / demo / retrieve use: --bank FILE or a bundle bank name; --prompts FILE (through
    `load_prompt_bank`: parsed once, cached by content hash); else the bundle's default bank."""
    from ago_runtime.vocab.bank import PromptBank, check_bank_for_bundle, load_prompt_bank

    if prompts and bank:
        raise AgoInputError(None, "give --prompts or --bank, not both")
    if bank:
        if Path(bank).is_file():
            return check_bank_for_bundle(PromptBank.load(bank), bank, bundle)
        if bank in bundle.banks:
            return bundle.load_bank(bank)
        raise AgoInputError(bank, f"prompt bank file not found (the bundle ships {sorted(bundle.banks)})")
    if prompts:
        return load_prompt_bank(resolve_prompts(prompts), bundle=bundle)
    return bundle.load_bank()


def iter_frames(images: Path, sample, info: Optional[Path], fallback_rig) -> Iterator[tuple]:
    """Yields (name, images dict, rig, source) per frame. `sample`: None (every frame), or sample tokens
    and/or scene names (a str or a list; each scene gives its keyframes in time order)."""
    return open_frames(images, sample, info, fallback_rig)[1]


def open_frames(images: Path, sample, info: Optional[Path], fallback_rig) -> tuple[int, Iterator[tuple]]:
    """(number of frames, iter_frames' iterator): the count is known before any image is decoded; bad
    arguments (a missing folder, an unknown sample) raise here."""
    from ago_runtime.formats.calibration import find_camera_images, load_images_folder

    wanted = [sample] if isinstance(sample, str) else list(sample or [])
    if info is not None:
        from ago_runtime.formats.mmdet3d_info import load_mmdet3d_info

        frames = load_mmdet3d_info(info, images if images is not None else info.parent)
        if wanted:
            unknown = [w for w in wanted if not any(w in (f.token, f.scene) for f in frames)]
            if unknown:
                raise AgoInputError(info, f"no sample or scene {', '.join(map(repr, unknown))}")
            frames = [f for w in wanted for f in frames if w in (f.token, f.scene)]
        return len(frames), ((f.token, f.images, f.rig, str(info)) for f in frames)
    if images is None:
        raise AgoInputError(None, "give --images DIR (or --info PKL)")
    images = Path(images)
    if not images.is_dir():
        raise AgoInputError(images, "images folder not found")
    if any(p.is_dir() and p.name.startswith("v1.0") for p in images.iterdir()):
        from ago_runtime.formats.nuscenes import NuScenesDataset

        ds = NuScenesDataset(images, load_extras=False)
        indices = list(ds.indices_of(wanted) if wanted else range(len(ds)))

        def dataset_frames():
            for i in indices:
                f = ds[i]
                yield f.token, f.images, f.rig, str(images)
        return len(indices), dataset_frames()
    if wanted:
        raise AgoInputError("--sample", f"{images} is an images folder (one frame), not a dataset")
    find_camera_images(images)

    def folder_frame():
        imgs, rig, _ = load_images_folder(images, fallback_rig=fallback_rig)
        yield images.resolve().name, imgs, rig, str(images)
    return 1, folder_frame()


PICTURES = ("full", "bev", "none")


def prediction_picture(pred, images: dict | None, title: str = "", kind: str = "full") -> np.ndarray:
    """The PNG of one prediction. kind "full": class BEV, entropy BEV, adapted-branch share, legend and
    the six cameras; "bev": the class BEV and the legend only (a few ms)."""
    from ago_runtime.pictures import render
    from ago_runtime.predict.predictor import UNEXPLAINED_THRESHOLD

    colors = render.palette_for(pred.class_names)
    colors = np.concatenate([colors, np.array([[240, 240, 240]], np.uint8)])
    scale = max(3, 360 // max(pred.semantics.shape[:2]))
    bev = render.bev_image(pred.semantics, colors=colors, free_index=pred.free_index, grid=pred.grid, scale=scale)
    panels = [(f"classes ({pred.identifier})", bev)]
    if kind == "full":
        occupied = pred.semantics != pred.free_index
        ent = render.scalar_bev(pred.entropy, mask=occupied, label="entropy (nats)", grid=pred.grid, scale=scale)
        panels.append(("entropy, max over z", ent))
        if pred.identifier != "none":
            share = render.scalar_bev(pred.branch.astype(np.float32), reduce="mean", mask=occupied, vmin=0, vmax=1,
                                      label="adapted share", grid=pred.grid, scale=scale)
            panels.append(("identifier: adapted branch share", share))
        if pred.unexplained is not None:
            unexp = render.scalar_bev(pred.unexplained, reduce="max", mask=pred.occupancy > 0.5, vmin=0, vmax=1,
                                      label="unexplained score", grid=pred.grid, scale=scale)
            panels.append((f"unexplained obstacles (> {UNEXPLAINED_THRESHOLD:g} = flagged)", unexp))
    top = render.side_by_side(panels)
    parts = [top, render.legend(pred.class_names, colors[:-1], width=top.shape[1])]
    if images and kind == "full":
        parts.append(render.rig_mosaic(images, width=top.shape[1]))
    picture = render.stack_vertical(parts)
    return render.with_title(picture, title) if title else picture   # the full name, wrapped, never cut


def _read_ahead(frames, read, outbox: queue.Queue, stop: threading.Event) -> None:
    """Reader thread: read(frame) for each frame onto `outbox`, then None; an exception is put on the
    queue instead (the consumer re-raises it). Stops early when `stop` is set."""
    try:
        for frame in frames:
            if stop.is_set():
                return
            outbox.put(read(frame))
        outbox.put(None)
    except BaseException as e:  # handed to the main thread
        outbox.put(e)


class _Writer(threading.Thread):
    """Writer thread: write(item) for each item of `inbox` until None. The first exception is kept in
    `error` (the main thread re-raises it) and later items are dropped, so the queue never blocks."""

    def __init__(self, write, inbox: queue.Queue):
        super().__init__(daemon=True)
        self.write, self.inbox = write, inbox
        self.error: BaseException | None = None

    def run(self) -> None:
        while (item := self.inbox.get()) is not None:
            if self.error is None:
                try:
                    self.write(item)
                except BaseException as e:
                    self.error = e


def auto_workers(frames: int) -> int:
    """Frames predicted at once by `ago infer`: 2 over a dataset on a multi-core CPU (each with half the
    cores' onnxruntime threads: two one-thread frames at once beat one two-thread frame, measured 0.172 ->
    0.125 s a frame on 2 cores, docs/runtime.md), 1 for a single frame (which then gets every core)."""
    return 2 if frames > 1 and (os.cpu_count() or 1) >= 2 else 1


def run_infer(images, prompts, bank, bundle, out, identifier, save_volumes, sample=None, info=None,
              int8=False, picture: str = "full", warm_up: bool = False, workers: int | None = None) -> list[Path]:
    """Predict every frame; three stages overlap (threads; numpy, OpenCV and onnxruntime release the GIL):
    a reader decodes and preprocesses the next frames and a writer writes the previous ones (npz, PNG, in
    frame order) while `workers` threads run the graphs and heads of the current ones (one Predictor, its
    sessions with cpu_count // workers threads each; None = auto_workers). The first frame is read and checked before
    anything is written, while the onnxruntime sessions open in another thread; an error in any stage ends
    the run with that error (the files written before it are complete: every file is written atomically).
    warm_up: run the graphs once on dummy inputs before the first frame; off by default here: the dummy frame
    costs a whole frame (~0.2 s) to save the first real frame ~0.04 s of first-run allocations (measured on a
    quiet machine, benchmarks/infer_ab.py --vary warm_up); an interactive Predictor keeps it on."""
    from ago_runtime.atomic import save_npz
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from ago_runtime.progress import track
    from concurrent.futures import ThreadPoolExecutor

    from ago_runtime.predict.predictor import Predictor, prepare_inputs
    from ago_runtime.pictures.render import save_png

    from ago_runtime.predict.bundle import card_line
    from ago_runtime.outputs import check_output_dir

    from ago_runtime.predict.heads import IDENTIFIERS

    one_line_warnings()
    if identifier is not None and identifier not in IDENTIFIERS:
        raise AgoInputError("--identifier", f"must be one of {', '.join(IDENTIFIERS)}, got {identifier!r}")
    if picture not in PICTURES:
        raise AgoInputError("--picture", f"must be one of {', '.join(PICTURES)}, got {picture!r}")
    if workers is not None and not 1 <= int(workers) <= 64:
        raise AgoInputError("--workers", f"must be between 1 and 64, got {workers}")
    check_output_dir(out, "--out")   # before any work
    b = Bundle.load(resolve_bundle(bundle))
    typer.echo(card_line(b))   # stdout: information; stderr keeps only warnings and the one error line
    chosen = choose_bank(b, prompts, bank)
    b.check_bank(chosen)   # the bank's text encoder and width, before any work
    identifier = identifier or b.identifier_for(chosen)   # none for a closed-world bank
    count, frames = open_frames(Path(images) if images else None, sample, Path(info) if info else None, b.rig)
    workers = int(workers) if workers is not None else auto_workers(count)
    threads = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else None
    out = Path(out)
    opened: dict = {}

    def open_predictor():
        try:
            opened["predictor"] = Predictor(b, int8=int8, threads=threads, warm_up=warm_up)
            opened["folded"] = opened["predictor"].fold(chosen)
        except BaseException as e:   # re-raised by the main thread
            opened["error"] = e

    opener = threading.Thread(target=open_predictor, daemon=True)
    opener.start()

    def read(frame):
        name, imgs, rig, source = frame
        t = time.perf_counter()
        x, m = prepare_inputs(b, imgs, rig, source)
        return name, imgs, x, m, time.perf_counter() - t

    def write(item):
        name, imgs, pred = item
        npz = out / f"{name}.npz"
        save_npz(npz, compresslevel=1, **pred.output_arrays(volumes=save_volumes))
        files = [npz]
        if picture != "none":
            files.append(save_png(out / f"{name}.png", prediction_picture(pred, imgs, name, picture)))
        t = pred.timings
        typer.echo(f"{name}: {' '.join(map(str, files))} (preprocess {t['preprocess']:.2f} s, encoder "
                   f"{t['encoder']:.2f} s, heads {t['heads']:.2f} s)", err=True)
        return files

    try:
        first = read(next(frames))      # reads and checks the first frame before anything is written
    finally:
        opener.join()
    if "error" in opened:
        raise opened["error"]
    predictor, folded = opened["predictor"], opened["folded"]
    prepared: queue.Queue = queue.Queue(maxsize=workers + 1)
    to_write: queue.Queue = queue.Queue(maxsize=workers + 1)
    stop = threading.Event()
    written: list[Path] = []
    reader = threading.Thread(target=_read_ahead, args=(frames, read, prepared, stop), daemon=True)
    writer = _Writer(lambda item: written.extend(write(item)), to_write)
    reader.start()
    writer.start()

    def stream():
        yield first
        while (item := prepared.get()) is not None:
            if isinstance(item, BaseException):
                raise item
            yield item

    def predict(item):
        name, imgs, x, m, t_pre = item
        pred = predictor.predict_arrays(x, m, chosen, identifier, folded, volumes=save_volumes)
        pred.timings = {"preprocess": t_pre, **pred.timings}
        return name, imgs, pred

    pool = ThreadPoolExecutor(workers, thread_name_prefix="ago-infer") if workers > 1 else None
    in_flight: collections.deque = collections.deque()   # futures in frame order
    try:
        for item in track(stream(), "predicting", total=count):
            if writer.error is not None:
                break
            if pool is None:
                to_write.put(predict(item))
                continue
            in_flight.append(pool.submit(predict, item))
            if len(in_flight) >= workers:
                to_write.put(in_flight.popleft().result())
        while in_flight and writer.error is None:      # the last frames; their errors propagate
            to_write.put(in_flight.popleft().result())
    finally:
        if pool is not None:   # on an error: the frames already submitted are finished and written, in order
            while in_flight and writer.error is None:
                try:
                    to_write.put(in_flight.popleft().result())
                except BaseException:
                    break
            for fut in in_flight:
                fut.cancel()
            pool.shutdown(wait=True)
        stop.set()
        while reader.is_alive():           # unblock a reader waiting on a full queue
            try:
                prepared.get(timeout=0.05)
            except queue.Empty:
                pass
        to_write.put(None)
        writer.join()
    if writer.error is not None:
        raise writer.error
    return written


def register(app: typer.Typer) -> None:
    @app.command("infer")
    def infer_cmd(
        images: Optional[Path] = typer.Option(None, "--images", help="images folder, nuScenes dataset, or data root for --info"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (e.g. prompts/ow.txt); default: the bundle's training classes"),
        bank: Optional[str] = typer.Option(None, "--bank", help="a prompt bank .npz, or the name of a bank in the bundle"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder (default: $AGO_BUNDLE, then the shipped one)"),
        out: Path = typer.Option(Path("ago_out"), "--out", "-o", help="output folder"),
        identifier: Optional[str] = typer.Option(None, "--identifier", help="min-entropy | max-conf | none (default: the bundle's open-world identifier when the prompts hold classes it was not trained on, else none)"),
        save_volumes: bool = typer.Option(False, "--save-volumes", help="also save entropy, confidence, branch and the unexplained-obstacle score and mask (drawn in the PNG)"),
        sample: Optional[List[str]] = typer.Option(None, "--sample", help="a dataset's sample token or scene name "
                                                   "(repeatable: several frames, one bundle load)"),
        info: Optional[Path] = typer.Option(None, "--info", help="mmdetection3d info .pkl"),
        int8: bool = typer.Option(False, "--int8", help="use the bundle's int8 encoder (needs a bundle exported "
                                  "with `ago export --int8`; faster, less exact: docs/runtime.md)"),
        picture: str = typer.Option("full", "--picture", help="PNG per frame: full (BEVs, legend, cameras), "
                                    "bev (class BEV + legend, cheap) or none"),
        workers: Optional[int] = typer.Option(None, "--workers", help="frames predicted at once (default: 2 over "
                                              "a dataset on a multi-core CPU, else 1; each worker holds a frame's "
                                              "activations)"),
    ) -> None:
        """Predict 3D occupancy for camera images with an exported bundle (numpy + onnxruntime)."""
        run_infer(images, prompts, bank, bundle, out, identifier, save_volumes, sample, info, int8, picture,
                  workers=workers)

    @app.command("demo")
    def demo_cmd(
        out: Path = typer.Option(Path("ago_demo"), "--out", "-o", help="output folder"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder (default: the shipped one)"),
        prompts: Optional[str] = typer.Option(None, "--prompts", help="prompt file (default: the bundle's classes)"),
    ) -> None:
        """Run `ago infer` on the shipped demo frame with the shipped default bundle."""
        from ago_runtime.predict.bundle import DEMO_FRAME_DIR, HOW_TO_MAKE_DEFAULT

        if not DEMO_FRAME_DIR.is_dir():
            raise AgoInputError(DEMO_FRAME_DIR, f"no demo frame installed; {HOW_TO_MAKE_DEFAULT}")
        written = run_infer(DEMO_FRAME_DIR, prompts, None, bundle, out, None, True)
        typer.echo(f"demo written to {out}/ ({', '.join(p.name for p in written)})")

    @app.command("retrieve")
    def retrieve_cmd(
        phrase: str = typer.Option(..., "--phrase", help='what to look for, e.g. "traffic cone"'),
        images: Path = typer.Option(..., "--images", help="images folder (six CAM_*.jpg + calib.json)"),
        bundle: Optional[Path] = typer.Option(None, "--bundle", help="bundle folder"),
        out: Path = typer.Option(Path("ago_retrieve"), "--out", "-o", help="output folder"),
    ) -> None:
        """Similarity of every voxel to a phrase (cosine, on the adapted VLM-aligned branch) + a BEV picture."""
        run_retrieve(phrase, images, bundle, out)


def run_retrieve(phrase: str, images: Path, bundle, out: Path) -> list[Path]:
    from ago_runtime.pictures import render
    from ago_runtime.atomic import save_npz
    from ago_runtime.predict.bundle import Bundle, resolve_bundle
    from ago_runtime.predict.heads import phrase_similarity
    from ago_runtime.predict.predictor import Predictor
    from ago_runtime.vocab.text_encoder import bundle_text_encoder

    from ago_runtime.outputs import check_output_dir

    one_line_warnings()
    if not phrase.strip():
        raise AgoInputError("--phrase", "is empty")
    check_output_dir(out, "--out")
    b = Bundle.load(resolve_bundle(bundle))
    direction = np.asarray(bundle_text_encoder(b).encode([phrase]), np.float32)[0]
    predictor = Predictor(b)
    bank = choose_bank(b, None, None)
    predictor.fold(bank)
    [(name, imgs, rig, source)] = list(iter_frames(Path(images), None, None, b.rig))
    h, g = predictor.encode(imgs, rig, source)
    pred = predictor.predict_hidden(h, g, bank, b.identifier)
    # the adapted branch F~_3D everywhere: it is the embedding aligned with the VLM's image space, the one that
    # can know phrases no training class had (benchmarks/results/retrieval_ap.md: unknown-class AP 6.4x the
    # prevalence on F~_3D, 1.1x on the identifier's per-voxel choice, which is mostly the grounded branch)
    sim = phrase_similarity(b.heads, h, g, np.ones(h.shape[0], np.uint8), direction).reshape(b.grid.shape)
    occupied = pred.semantics != pred.free_index
    slug = "".join(c if c.isalnum() else "_" for c in phrase.strip().lower())[:40]
    npz = out / f"{name}_{slug}.npz"
    save_npz(npz, similarity=sim, occupied=occupied.astype(np.uint8), phrase=np.array(phrase))
    colors = np.concatenate([render.palette_for(pred.class_names), np.array([[240, 240, 240]], np.uint8)])
    scale = max(3, 360 // max(b.grid.shape[:2]))
    picture = render.side_by_side([
        (f'similarity to "{phrase}" (occupied, max over z)',
         render.scalar_bev(sim, mask=occupied, label="cosine", grid=b.grid, scale=scale)),
        ("classes", render.bev_image(pred.semantics, colors=colors, free_index=pred.free_index, grid=b.grid,
                                     scale=scale))])
    png = render.save_png(out / f"{name}_{slug}.png", render.stack_vertical([picture, render.rig_mosaic(imgs, width=picture.shape[1])]))
    typer.echo(f"{npz} {png}", err=True)
    return [npz, png]
