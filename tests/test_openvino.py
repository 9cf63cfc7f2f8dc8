"""`--device openvino [--precision fp32|bf16]`: the bundle graphs on the OpenVINO runtime (ago_runtime/openvino_session.py).

fp32 must give onnxruntime's labels; bf16 is refused with one line where the CPU has no bf16 units or the
openvino package is missing (the flag reader is replaced here, so this runs on any CPU), and runs where both are
there; with OpenVINO's CPU device only the planes graph goes to OpenVINO (checked with a stand-in session on any
machine), and `--int8` runs its int8 planes graph there. Tests that open real OpenVINO sessions skip without the
openvino package (the `openvino` extra)."""

import os

import numpy as np
import pytest

from ago_runtime.errors import AgoInputError
from ago_runtime import providers
from ago_runtime.providers import Device, Precision, check_device


from conftest import ago_in_process, tiny_town  # noqa: E402

_ago = ago_in_process


def test_bf16_is_refused_with_one_line_on_a_cpu_without_bf16_units(monkeypatch, tmp_path):
    monkeypatch.setattr(providers, "openvino_installed", lambda: True)
    monkeypatch.setattr(providers, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_vnni"})
    with pytest.raises(AgoInputError, match=r"^--precision: bf16 needs a CPU with avx512_bf16 or amx_bf16 and this "
                                            r"CPU has neither .*use --precision fp32$"):
        check_device(Device.OPENVINO, Precision.BF16)
    check_device(Device.OPENVINO, Precision.FP32)          # fp32 needs no bf16 units
    out = tmp_path / "out"
    code, err = _ago(["demo", "--device", "openvino", "--precision", "bf16", "--out", out])
    assert code == 2 and err.startswith("error: --precision: bf16 needs a CPU with")
    assert err.count("\n") == 1 and not out.exists()        # one line, before any work
    monkeypatch.setattr(providers, "cpu_flags", lambda: {"avx512f", "amx_bf16"})
    check_device(Device.OPENVINO, Precision.BF16)           # AMX alone is enough


def test_openvino_is_refused_with_one_line_when_the_package_is_missing(monkeypatch, tmp_path):
    monkeypatch.setattr(providers, "openvino_installed", lambda: False)
    monkeypatch.setattr(providers, "cpu_flags", lambda: {"avx512_bf16"})
    with pytest.raises(AgoInputError, match=r"^--precision: bf16 runs through the OpenVINO runtime, which is not "
                                            r"installed; install: bash scripts/setup.sh --device openvino"):
        check_device(Device.OPENVINO, Precision.BF16)
    with pytest.raises(AgoInputError, match=r"^--device: openvino runs through the OpenVINO runtime"):
        check_device(Device.OPENVINO, Precision.FP32)
    code, err = _ago(["demo", "--device", "openvino", "--out", tmp_path / "out"])
    assert code == 2 and err.startswith("error: --device: openvino runs through the OpenVINO runtime")
    assert err.count("\n") == 1


def test_with_openvino_on_the_cpu_only_the_planes_graph_goes_to_it(monkeypatch):
    # OpenVINO replaced by onnxruntime sessions that say they are OpenVINO's: where each graph goes, on any machine
    import onnxruntime as ort

    from ago_runtime import cache, openvino_session
    from ago_runtime.predict.bundle import DEFAULT_BUNDLE_DIR, Bundle
    from ago_runtime.predict.encoder import open_encoder

    class FakeOpenVino(ort.InferenceSession):
        def get_providers(self):
            return ["OpenVINO:fake"]

    monkeypatch.setattr(cache, "check_device", lambda device, precision: None)
    monkeypatch.setattr(openvino_session, "open_openvino_session",
                        lambda path, threads, precision, cache_dir: FakeOpenVino(str(path), providers=["CPUExecutionProvider"]))
    b = Bundle.load(DEFAULT_BUNDLE_DIR)
    for precision in (Precision.FP32, Precision.BF16):
        enc = open_encoder(b, threads=2, warm_up=False, device=Device.OPENVINO, precision=precision)
        assert enc.planes.get_providers() == ["OpenVINO:fake"]
        stages = [s for ss in enc.sessions.values() for s, _ in ss]
        assert stages and all(s.get_providers() == ["CPUExecutionProvider"] for s in stages)
        assert enc.slab_pool is not None                  # onnxruntime's stages run in parallel slabs
    enc = open_encoder(b, threads=2, warm_up=False, device=Device.OPENVINO, precision=Precision.FP16)   # its GPU
    assert all(s.get_providers() == ["OpenVINO:fake"] for ss in enc.sessions.values() for s, _ in ss)
    assert enc.slab_pool is None


# ---------------------------------------------------------------------------- sessions (need openvino)
@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    pytest.importorskip("torch")
    pytest.importorskip("openvino")
    from ago_export.export import export_bundle
    from ago_export.testing import random_checkpoint

    root = tmp_path_factory.mktemp("openvino")
    os.environ["AGO_CACHE_DIR"] = str(root / "cache")
    ckpt = random_checkpoint(root / "tiny.pt", "tiny", prompts="cw", seed=3)
    town = tiny_town(root / "town")   # the int8 graph's calibration frames (a random checkpoint records none)
    export_bundle(ckpt, root / "bundle", int8=True, bank_prompts=[], real_frame=False, log=lambda s: None,
                  calibration_data=town)
    return root / "bundle"


def _labels(bundle_dir, frame, device, precision, int8=False):
    from ago_runtime.formats.calibration import load_images_folder
    from ago_runtime.predict.predictor import Predictor

    p = Predictor(bundle_dir, device=device, precision=precision, int8=int8)
    images, rig, _ = load_images_folder(frame, fallback_rig=p.bundle.rig)
    bank = p.bundle.load_bank()
    pred = p.predict(images, rig, bank, identifier="min-entropy")
    return p, pred


def _in_child(check, *args):
    """check(*args) in a fresh interpreter (spawn), its assertion errors raised here. Once OpenVINO's runtime has
    run in a process, a later child process that process starts can take it down without a Python-visible signal
    (seen as an xdist worker dying in a later test's subprocess.run or DataLoader workers); so the test process never
    loads OpenVINO itself."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as ex:
        return ex.submit(check, *args).result()


def _check_fp32_labels(bundle_dir, frame):
    _, ref = _labels(bundle_dir, frame, "cpu", "fp32")
    p, got = _labels(bundle_dir, frame, "openvino", "fp32")
    assert p.encoder.planes.get_providers() == ["OpenVINO:CPU:fp32"]
    assert all(s.get_providers() == ["CPUExecutionProvider"] for ss in p.encoder.sessions.values() for s, _ in ss)
    assert np.array_equal(got.semantics, ref.semantics)
    assert np.array_equal(got.branch, ref.branch)
    np.testing.assert_allclose(got.confidence, ref.confidence, atol=1e-4)


def test_openvino_fp32_gives_onnxruntimes_labels(bundle_dir, tmp_path):
    from ago_runtime.formats.random_frame import write_random_frame

    _in_child(_check_fp32_labels, bundle_dir, write_random_frame(tmp_path / "frame", seed=5))


def _check_int8_planes(bundle_dir, frame):
    _, ref = _labels(bundle_dir, frame, "cpu", "fp32", int8=True)
    p, got = _labels(bundle_dir, frame, "openvino", "fp32", int8=True)
    planes, stages = p.bundle.encoder_graphs("int8")
    assert p.encoder.planes_path == planes.path != bundle_dir / "planes.onnx"
    assert p.encoder.planes.get_providers() == ["OpenVINO:CPU:fp32"]
    assert all(s.get_providers() == ["CPUExecutionProvider"] for ss in p.encoder.sessions.values() for s, _ in ss)
    # the same QDQ graph through OpenVINO's int8 kernels: onnxruntime's int8 labels, up to rounding
    assert (got.semantics == ref.semantics).mean() > 0.97


def test_openvino_runs_the_int8_planes_graph(bundle_dir, tmp_path):
    from ago_runtime.formats.random_frame import write_random_frame

    _in_child(_check_int8_planes, bundle_dir, write_random_frame(tmp_path / "frame", seed=5))


def _check_each_thread_its_own_request(bundle_dir):
    from concurrent.futures import ThreadPoolExecutor

    from ago_runtime.openvino_session import open_openvino_session

    sess = open_openvino_session(bundle_dir / "voxels_0.onnx", threads=1)
    (x_arg,), (y_arg,) = sess.get_inputs(), sess.get_outputs()
    assert (x_arg.name, y_arg.name, x_arg.type) == ("x", "y", "tensor(float)") and not isinstance(x_arg.shape[0], int)
    xs = [np.random.default_rng(i).standard_normal((500 + 7 * i, x_arg.shape[1])).astype(np.float32) for i in range(8)]
    alone = [sess.run(["y"], {"x": x})[0] for x in xs]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda x: sess.run(["y"], {"x": x})[0], xs))
    for a, b in zip(alone, together):
        assert np.array_equal(a, b)


def test_openvino_session_gives_each_thread_its_own_request(bundle_dir):
    _in_child(_check_each_thread_its_own_request, bundle_dir)


def _check_bf16(bundle_dir, frame):
    _, ref = _labels(bundle_dir, frame, "openvino", "fp32")
    p, got = _labels(bundle_dir, frame, "openvino", "bf16")
    assert p.encoder.planes.get_providers() == ["OpenVINO:CPU:bf16"]
    assert got.semantics.shape == ref.semantics.shape
    # bf16 keeps 8 bits of mantissa: the labels mostly agree, and the confidences differ (it did run in bf16)
    assert (got.semantics == ref.semantics).mean() > 0.9
    assert not np.array_equal(got.confidence, ref.confidence)


@pytest.mark.skipif(not set(providers.BF16_FLAGS) & providers.cpu_flags(), reason="this CPU has no bf16 units")
def test_openvino_bf16_runs_where_the_cpu_has_bf16_units(bundle_dir, tmp_path):
    from ago_runtime.formats.random_frame import write_random_frame

    _in_child(_check_bf16, bundle_dir, write_random_frame(tmp_path / "frame", seed=5))
