"""The depth network runner on real onnxruntime CPU sessions with the generated test model."""

from __future__ import annotations

import hashlib
import os

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from autonomy.depth.network import (
    DepthNetwork,
    NetworkError,
    NetworkOptions,
    choose_providers,
    provider_options,
    resize_align_corners,
)
from autonomy.options import OptionError
from companion.tools.testmodel import build_test_model

MEAN = np.array([0.485, 0.456, 0.406])
STD = np.array([0.229, 0.224, 0.225])
CPU_ONLY = ["AzureExecutionProvider", "CPUExecutionProvider"]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Paths of the test model variants, written once for the module."""
    folder = tmp_path_factory.mktemp("models")
    variants = {
        "dynamic": build_test_model(),
        "rank4": build_test_model(output_rank=4),
        "fixed": build_test_model(fixed_size=(64, 96)),
        "fixed256": build_test_model(fixed_size=(256, 256)),
    }
    paths = {}
    for name, data in variants.items():
        paths[name] = folder / f"{name}.onnx"
        paths[name].write_bytes(data)
    return paths


def open_network(path, camera_size=(480, 640), **options) -> DepthNetwork:
    return DepthNetwork.open(NetworkOptions(model=str(path), **options), camera_size)


def write_model(tmp_path, nodes, inputs, outputs, initializers=()) -> str:
    """A small inline ONNX model for the mismatch tests, saved under tmp_path."""
    graph = helper.make_graph(nodes, "bad", inputs, outputs, initializer=list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path = tmp_path / "bad.onnx"
    path.write_bytes(model.SerializeToString())
    return str(path)


def image_input(name="image", channels=3, elem=TensorProto.FLOAT):
    return helper.make_tensor_value_info(name, elem, [1, channels, "h", "w"])


def random_bgr(height=480, width=640, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


# --- end to end ------------------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["dynamic", "rank4", "fixed"])
@pytest.mark.parametrize("preset", ["depth_anything_v2", "midas_v21_small"])
def test_runs_end_to_end_at_camera_resolution(models, variant, preset):
    network = open_network(models[variant], camera_size=(240, 320), preset=preset)
    depth = network(random_bgr(240, 320))
    assert depth.shape == (240, 320)
    assert depth.dtype == np.float32
    assert np.all(np.isfinite(depth)) and np.all(depth >= 0)


def test_output_follows_the_input_brightness(models):
    network = open_network(models["dynamic"])
    dark = network(np.full((480, 640), 40, np.uint8))
    bright = network(np.full((480, 640), 220, np.uint8))
    assert np.all(bright > dark)


def test_a_float16_model_gets_a_float16_input_and_gives_float32(tmp_path):
    reduce = helper.make_node("ReduceMean", ["image"], ["depth"], axes=[1], keepdims=0)
    path = write_model(tmp_path, [reduce], [image_input(elem=TensorProto.FLOAT16)],
                       [helper.make_tensor_value_info("depth", TensorProto.FLOAT16,
                                                      [1, "h", "w"])])
    depth = open_network(path)(random_bgr())
    assert depth.dtype == np.float32 and depth.shape == (480, 640)


# --- Depth Anything V2 preprocessing ---------------------------------------------------------

def reference_get_size(height, width, size, multiple, method):
    """The reference util/transform.py Resize.get_size with keep_aspect_ratio=True."""
    def constrain(x, min_val=0, max_val=None):
        y = int(np.round(x / multiple) * multiple)
        if max_val is not None and y > max_val:
            y = int(np.floor(x / multiple) * multiple)
        if y < min_val:
            y = int(np.ceil(x / multiple) * multiple)
        return y

    scale_h, scale_w = size / height, size / width
    if method == "lower_bound":
        scale = max(scale_h, scale_w)
        return constrain(scale * height, min_val=size), constrain(scale * width, min_val=size)
    scale = min(scale_h, scale_w)
    return constrain(scale * height, max_val=size), constrain(scale * width, max_val=size)


def keys_cubic(x, a=-0.75):
    """Keys' cubic convolution kernel with OpenCV's and PyTorch's a = -0.75."""
    x = np.abs(x)
    near = ((a + 2) * x - (a + 3)) * x * x + 1
    far = ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
    return np.where(x <= 1, near, np.where(x < 2, far, 0.0))


def exact_cubic_resize(image, height, width):
    """Bicubic resize in float64: half-pixel centres, source x = (x + 0.5) w_in / w_out - 0.5,
    four taps, edge pixels replicated."""
    for axis, n in ((0, height), (1, width)):
        m = image.shape[axis]
        x = (np.arange(n) + 0.5) * m / n - 0.5
        x0 = np.floor(x).astype(int)
        shape = [1] * image.ndim
        shape[axis] = n
        image = sum(np.take(image, np.clip(x0 + k, 0, m - 1), axis=axis)
                    * keys_cubic(x - x0 - k).reshape(shape) for k in range(-1, 3))
    return image


def reference_preprocess(bgr, size, multiple, method, resize=None):
    """The reference pipeline in float64: cvtColor, / 255, bicubic resize, normalise, CHW."""
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) / 255.0
    h, w = reference_get_size(*bgr.shape[:2], size, multiple, method)
    if resize is None:
        resized = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_CUBIC)
    else:
        resized = resize(rgb, h, w)
    return ((resized - MEAN) / STD).transpose(2, 0, 1)[np.newaxis]


#: OpenCV's own float64 INTER_CUBIC differs from exact cubic convolution by up to 0.011 grey
#: levels (its float32 path by 7e-5), i.e. 0.011 / (255 x 0.224) = 1.9e-4 after normalising.
OPENCV_F64_TOLERANCE = 3e-4


def test_da_v2_input_size_keeps_the_short_side_at_518(models):
    network = open_network(models["dynamic"])
    # 518 / 480 = 1.079; 640 x 1.079 = 690.7 = 49.33 x 14 -> 49 x 14 = 686 >= 518.
    assert network.input_size_for(480, 640) == (518, 686)
    assert reference_get_size(480, 640, 518, 14, "lower_bound") == (518, 686)


def test_da_v2_input_size_266(models):
    network = open_network(models["dynamic"], input_size=266)
    # 266 / 480 = 0.5542; 640 x 0.5542 = 354.7 = 25.33 x 14 -> 25 x 14 = 350 >= 266;
    # 480 x 0.5542 = 266 = 19 x 14.
    assert network.input_size_for(480, 640) == (266, 350)


def test_da_v2_constant_colour_is_normalised_per_rgb_channel(models):
    network = open_network(models["dynamic"])
    bgr = np.empty((480, 640, 3), np.uint8)
    bgr[...] = (10, 120, 250)
    tensor = network.preprocess(bgr)
    assert tensor.shape == (1, 3, 518, 686) and tensor.dtype == np.float32
    assert tensor.flags.c_contiguous
    expected = (np.array([250, 120, 10]) / 255 - MEAN) / STD
    for channel in range(3):
        np.testing.assert_allclose(tensor[0, channel], expected[channel], atol=2e-6)


def test_da_v2_channel_order_is_rgb_from_a_bgr_image(models):
    network = open_network(models["dynamic"])
    blue = np.zeros((48, 64, 3), np.uint8)
    blue[..., 0] = 255
    tensor = network.preprocess(blue)
    np.testing.assert_allclose(tensor[0, 2], (1 - MEAN[2]) / STD[2], atol=2e-6)
    np.testing.assert_allclose(tensor[0, 0], -MEAN[0] / STD[0], atol=2e-6)
    rgb = blue[..., ::-1].copy()
    np.testing.assert_array_equal(network.preprocess(rgb, channels="rgb"), tensor)


@pytest.mark.parametrize("preset, size, multiple, method, seed", [
    ("depth_anything_v2", 518, 14, "lower_bound", 3),
    ("midas_v21_small", 256, 32, "upper_bound", 5),
])
def test_preprocessing_matches_the_float64_reference_on_a_random_image(
        models, preset, size, multiple, method, seed):
    network = open_network(models["dynamic"], preset=preset)
    bgr = random_bgr(seed=seed)
    tensor = network.preprocess(bgr)
    exact = reference_preprocess(bgr, size, multiple, method, exact_cubic_resize)
    np.testing.assert_allclose(tensor, exact, rtol=0, atol=1e-5)
    literal = reference_preprocess(bgr, size, multiple, method)
    np.testing.assert_allclose(tensor, literal, rtol=0, atol=OPENCV_F64_TOLERANCE)


def test_grey_input_equals_the_replicated_colour_input(models):
    network = open_network(models["dynamic"])
    grey = random_bgr(seed=4)[..., 0].copy()
    np.testing.assert_array_equal(network.preprocess(grey),
                                  network.preprocess(np.dstack([grey] * 3)))


# --- MiDaS preprocessing ---------------------------------------------------------------------

def test_midas_input_size_fits_the_long_side_in_256(models):
    network = open_network(models["dynamic"], preset="midas_v21_small")
    # 256 / 640 = 0.4; 480 x 0.4 = 192 = 6 x 32.
    assert network.input_size_for(480, 640) == (192, 256)


def test_a_fixed_shape_model_gets_exactly_its_shape(models):
    network = open_network(models["fixed256"], preset="midas_v21_small")
    assert network.input_size_for(480, 640) == (256, 256)
    bgr = random_bgr(seed=6)
    resized = exact_cubic_resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) / 255.0, 256, 256)
    expected = ((resized - MEAN) / STD).transpose(2, 0, 1)[np.newaxis]
    np.testing.assert_allclose(network.preprocess(bgr), expected, rtol=0, atol=1e-5)


# --- postprocessing --------------------------------------------------------------------------

def bilinear_align_corners(image, height, width):
    """Exact float64 bilinear interpolation at x (w_in - 1) / (w_out - 1), likewise y."""
    h, w = image.shape
    y = np.arange(height) * (h - 1) / (height - 1)
    x = np.arange(width) * (w - 1) / (width - 1)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    a = image.astype(np.float64)
    return ((a[y0][:, x0] * (1 - fx) + a[y0][:, x0 + 1] * fx) * (1 - fy)
            + (a[y0 + 1][:, x0] * (1 - fx) + a[y0 + 1][:, x0 + 1] * fx) * fy)


@pytest.mark.parametrize("shape", [(518, 686), (37, 49), (2, 3)])
def test_da_v2_upsampling_is_bilinear_with_aligned_corners(models, shape):
    network = open_network(models["dynamic"])
    output = np.random.default_rng(7).uniform(0, 10, shape).astype(np.float32)
    upsampled = network.postprocess(output, (480, 640))
    assert upsampled.shape == (480, 640) and upsampled.dtype == np.float32
    # OpenCV places samples on a 1/32 pixel grid: at most 1/64 px off per axis, so the value
    # is off by at most 1/64 of the largest neighbour step along each axis.
    steps = np.abs(np.diff(output, axis=0)).max() + np.abs(np.diff(output, axis=1)).max()
    np.testing.assert_allclose(upsampled, bilinear_align_corners(output, 480, 640),
                               rtol=0, atol=steps / 64 + 1e-5)
    for corner in [(0, 0), (0, -1), (-1, 0), (-1, -1)]:
        assert upsampled[corner] == output[corner]


def test_resize_align_corners_to_a_single_pixel_takes_the_first():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert resize_align_corners(image, 1, 1)[0, 0] == 0.0


def test_midas_upsampling_is_bicubic_with_half_pixel_centres(models):
    network = open_network(models["dynamic"], preset="midas_v21_small")
    output = np.random.default_rng(8).uniform(0, 10, (192, 256)).astype(np.float32)
    upsampled = network.postprocess(output, (480, 640))
    assert upsampled.shape == (480, 640) and upsampled.dtype == np.float32
    np.testing.assert_allclose(upsampled, exact_cubic_resize(output, 480, 640), atol=1e-4)


# --- providers -------------------------------------------------------------------------------

def test_choose_providers_drops_the_unavailable():
    assert choose_providers(("tensorrt", "cuda", "cpu"), CPU_ONLY) == ["CPUExecutionProvider"]


def test_choose_providers_keeps_the_configured_order():
    available = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert choose_providers(("cpu", "tensorrt"), available) == [
        "CPUExecutionProvider", "TensorrtExecutionProvider"]
    assert choose_providers(("cuda", "cpu", "cuda"), available) == [
        "CUDAExecutionProvider", "CPUExecutionProvider"]


def test_choose_providers_with_none_available_names_both_sides():
    with pytest.raises(NetworkError, match=r"tensorrt, cuda.*AzureExecutionProvider, "
                                           r"CPUExecutionProvider"):
        choose_providers(("tensorrt", "cuda"), CPU_ONLY)


def test_default_providers_fall_back_to_the_cpu_here(models, caplog):
    network = open_network(models["dynamic"])
    assert network.provider == "CPUExecutionProvider"
    assert "not on the preferred TensorrtExecutionProvider" in caplog.text


def test_the_network_reports_its_options_and_preset(models):
    network = open_network(models["dynamic"], preset="midas_v21_small", threads=1)
    assert network.preset.name == "midas_v21_small"
    assert network.options.threads == 1


# --- start-up errors -------------------------------------------------------------------------

def test_no_model_given():
    with pytest.raises(NetworkError, match=r"no depth model given.*\[depth_network\] model"):
        DepthNetwork.open(NetworkOptions())


def test_missing_file_names_the_path(tmp_path):
    path = tmp_path / "absent.onnx"
    with pytest.raises(NetworkError, match=rf"cannot read the depth model {path}: No such"):
        open_network(path)


def test_a_directory_is_not_a_model(tmp_path):
    with pytest.raises(NetworkError, match=rf"cannot read the depth model {tmp_path}: Is a dir"):
        open_network(tmp_path)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root reads files whatever their mode")
def test_an_unreadable_file_names_the_path(models, tmp_path):
    path = tmp_path / "locked.onnx"
    path.write_bytes(models["dynamic"].read_bytes())
    path.chmod(0)
    try:
        with pytest.raises(NetworkError, match=rf"cannot read .*{path}: Permission denied"):
            open_network(path)
    finally:
        path.chmod(0o600)


def test_garbage_bytes_are_not_an_onnx_model(tmp_path):
    path = tmp_path / "garbage.onnx"
    path.write_bytes(b"\x00\xffnot a model" * 50)
    with pytest.raises(NetworkError, match=rf"onnxruntime cannot load the depth model {path}"):
        open_network(path)


def test_sha256_mismatch_names_both_digests(models):
    expected = "0" * 64
    actual = hashlib.sha256(models["dynamic"].read_bytes()).hexdigest()
    with pytest.raises(NetworkError, match=rf"has sha256 {actual}, but .* expects {expected}"):
        open_network(models["dynamic"], sha256=expected)


def test_matching_sha256_opens_in_either_case(models):
    digest = hashlib.sha256(models["dynamic"].read_bytes()).hexdigest()
    assert open_network(models["dynamic"], sha256=digest.upper()).provider


def test_a_one_channel_input_is_a_mismatched_model(tmp_path):
    path = write_model(tmp_path, [helper.make_node("Relu", ["image"], ["depth"])],
                       [image_input(channels=1)],
                       [helper.make_tensor_value_info("depth", TensorProto.FLOAT,
                                                      [1, 1, "h", "w"])])
    with pytest.raises(NetworkError, match=r"mismatched model .*'image' has 1 channels"):
        open_network(path)


def test_two_inputs_are_a_mismatched_model(tmp_path):
    add = helper.make_node("Add", ["image", "other"], ["depth"])
    path = write_model(tmp_path, [add], [image_input(), image_input("other")],
                       [helper.make_tensor_value_info("depth", TensorProto.FLOAT,
                                                      [1, 3, "h", "w"])])
    with pytest.raises(NetworkError, match=r"mismatched model .*2 inputs \(image, other\)"):
        open_network(path)


def test_an_output_that_is_not_one_image_is_a_mismatched_model(tmp_path):
    weights = numpy_helper.from_array(np.ones((2, 3, 1, 1), np.float32), "w")
    conv = helper.make_node("Conv", ["image", "w"], ["depth"])
    path = write_model(tmp_path, [conv], [image_input()],
                       [helper.make_tensor_value_info("depth", TensorProto.FLOAT,
                                                      [1, 2, "h", "w"])], [weights])
    with pytest.raises(NetworkError, match=r"mismatched model .*shape \(1, 2, 518, 686\)"):
        open_network(path)


@pytest.mark.parametrize("image, channels, message", [
    (np.zeros((48, 64, 3), np.float32), "bgr", "uint8 images, got float32"),
    (np.zeros((48, 64, 4), np.uint8), "bgr", r"got shape \(48, 64, 4\)"),
    (np.zeros((48, 64, 3), np.uint8), "xyz", "channels must be 'bgr' or 'rgb', got 'xyz'"),
    (np.zeros((0, 64), np.uint8), "bgr", "empty image"),
])
def test_bad_images_are_refused(models, image, channels, message):
    network = open_network(models["dynamic"])
    with pytest.raises(ValueError, match=message):
        network(image, channels=channels)


# --- options ---------------------------------------------------------------------------------

@pytest.mark.parametrize("digest", ["abc", "g" * 64, "0" * 63])
def test_sha256_must_be_64_hex_digits(digest):
    with pytest.raises(OptionError, match="sha256: must be 64 hexadecimal digits"):
        NetworkOptions(sha256=digest)


def test_input_size_must_be_a_multiple_of_the_presets():
    with pytest.raises(OptionError, match=r"input_size 500 is not a multiple of 14 "
                                          r"\(depth_anything_v2\); try 490 or 504"):
        NetworkOptions(input_size=500)
    with pytest.raises(OptionError, match=r"not a multiple of 32 \(midas_v21_small\); try 32$"):
        NetworkOptions(preset="midas_v21_small", input_size=20)
    assert NetworkOptions(input_size=266).input_size == 266


def test_unknown_or_no_provider_is_refused():
    with pytest.raises(OptionError, match="providers: must be one of tensorrt, cuda, cpu; "
                                          "got 'gpu'"):
        NetworkOptions(providers=("cuda", "gpu"))
    with pytest.raises(OptionError, match="providers: must name at least one"):
        NetworkOptions(providers=())


def test_unknown_preset_and_negative_threads_are_refused():
    with pytest.raises(OptionError, match="preset: must be one of"):
        NetworkOptions(preset="zoedepth")
    with pytest.raises(OptionError, match="threads: must be >= 0"):
        NetworkOptions(threads=-1)


def test_tensorrt_options_use_onnxruntime_names():
    options = NetworkOptions(tensorrt_fp16=False, tensorrt_cache_dir="/var/cache/trt")
    assert provider_options("TensorrtExecutionProvider", options) == {
        "trt_fp16_enable": "False", "trt_engine_cache_enable": "True",
        "trt_engine_cache_path": "/var/cache/trt"}
    assert provider_options("CUDAExecutionProvider", options) == {}
    assert provider_options("TensorrtExecutionProvider", NetworkOptions()) == {
        "trt_fp16_enable": "True"}
