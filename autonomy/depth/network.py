"""The depth network runner: an ONNX relative-depth model under onnxruntime.

A :class:`DepthNetwork` turns a camera image into the network's relative output (disparity or
inverse depth, larger = nearer) at the camera's resolution, with the pre- and post-processing
of the model's reference code, described by a :class:`Preset`:

- ``depth_anything_v2``: Depth Anything V2 (Yang et al. 2024), reference
  ``depth_anything_v2/dpt.py`` ``image2tensor`` and ``util/transform.py``;
- ``midas_v21_small``: MiDaS v2.1 small (Ranftl et al. 2020), reference
  ``midas/model_loader.py`` for ``midas_v21_small_256``.

:meth:`DepthNetwork.open` is the one place in ``autonomy/`` that reads a file: the model, once,
at start-up. It checks everything that can be checked before arming (the file, its digest, the
model's interface, one warm-up inference) and raises :class:`NetworkError` with a message an
operator can act on. After that the runner does no I/O. It does not judge the output's values
(NaN, negative): the caller's validation does.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnxruntime

from autonomy.options import OptionError, option, validate

log = logging.getLogger(__name__)

#: Provider names in the config -> onnxruntime's execution provider names.
PROVIDERS = {
    "tensorrt": "TensorrtExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "cpu": "CPUExecutionProvider",
}


class NetworkError(Exception):
    """The depth network cannot start: a missing, unreadable or mismatched model."""


@dataclass(frozen=True)
class Preset:
    """How one family of models wants its input and how its output is brought back.

    The input image is resized keeping its aspect ratio so that both sides are multiples of
    ``multiple_of`` and, for ``resize="lower_bound"``, the short side is at least the input size
    (Depth Anything V2), or, for ``"upper_bound"``, the long side is at most the input size
    (MiDaS); bicubic (``cv2.INTER_CUBIC``). Pixel values are normalised as
    ``(rgb / 255 - mean) / std``. The output is upsampled to the camera's resolution with
    ``upsample``: ``"bilinear_align_corners"`` or ``"bicubic"`` (half-pixel centres).
    """

    name: str
    default_size: int
    multiple_of: int
    resize: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    upsample: str
    output: str


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

PRESETS = {
    preset.name: preset
    for preset in (
        Preset("depth_anything_v2", 518, 14, "lower_bound", IMAGENET_MEAN, IMAGENET_STD,
               "bilinear_align_corners", "relative disparity"),
        Preset("midas_v21_small", 256, 32, "upper_bound", IMAGENET_MEAN, IMAGENET_STD,
               "bicubic", "relative inverse depth"),
    )
}

_HEX64 = re.compile(r"[0-9a-fA-F]{64}")


@dataclass(frozen=True)
class NetworkOptions:
    """Which ONNX model to run, how to feed it and where (config section ``[depth_network]``)."""

    model: str = option("", doc="path of the ONNX depth model; empty = none")
    sha256: str = option("", doc="expected SHA-256 hex digest of the model file; empty = "
                         "not checked")
    preset: str = option("depth_anything_v2", choices=tuple(PRESETS),
                         doc="pre- and post-processing of the model's reference code")
    input_size: int = option(0, ge=0, doc="network input size in pixels (short side for "
                             "depth_anything_v2, long side for midas_v21_small); 0 = the "
                             "preset's default (518, 256)")
    providers: tuple[str, ...] = option(("tensorrt", "cuda", "cpu"), choices=tuple(PROVIDERS),
                                        doc="onnxruntime execution providers, most wanted "
                                        "first; unavailable ones are skipped")
    threads: int = option(0, ge=0, doc="onnxruntime intra-op threads; 0 = onnxruntime's "
                          "default")
    tensorrt_fp16: bool = option(True, doc="let TensorRT run layers in half precision")
    tensorrt_cache_dir: str = option("", doc="folder of TensorRT's engine cache; empty = "
                                     "no cache (the engine is rebuilt at every start)")

    def __post_init__(self) -> None:
        validate(self)
        if self.sha256 and not _HEX64.fullmatch(self.sha256):
            raise OptionError("sha256", f"must be 64 hexadecimal digits (the output of "
                              f"`sha256sum MODEL`), got {self.sha256!r}")
        if not self.providers:
            raise OptionError("providers", "must name at least one of "
                              f"{', '.join(PROVIDERS)}")
        network_input_size(self)


def network_input_size(options: NetworkOptions) -> int:
    """The preset's input size: ``options.input_size``, or the preset's default for 0.

    Raises :class:`OptionError` when it is not a multiple of the preset's ``multiple_of``.
    """
    preset = PRESETS[options.preset]
    size = options.input_size or preset.default_size
    m = preset.multiple_of
    if size % m:
        below, above = (size // m) * m, (size // m + 1) * m
        hint = f"try {below} or {above}" if below else f"try {above}"
        raise OptionError("input_size", f"input_size {size} is not a multiple of {m} "
                          f"({preset.name}); {hint}")
    return size


def constrain_to_multiple(x: float, multiple: int, *, min_val: int = 0,
                          max_val: int | None = None) -> int:
    """``round(x / m) * m``; ``floor`` instead if that exceeds ``max_val``, ``ceil`` if it is
    below ``min_val`` (reference ``Resize.constrain_to_multiple_of``, numpy's round half to
    even)."""
    y = int(np.round(x / multiple) * multiple)
    if max_val is not None and y > max_val:
        y = int(math.floor(x / multiple) * multiple)
    if y < min_val:
        y = int(math.ceil(x / multiple) * multiple)
    return y


def keep_aspect_size(height: int, width: int, size: int, preset: Preset) -> tuple[int, int]:
    """(h, w) of the network input for a ``height`` x ``width`` image (reference
    ``Resize.get_size`` with ``keep_aspect_ratio=True``).

    One scale ``s`` for both sides: ``lower_bound`` takes ``s = size / min(height, width)`` so
    the short side becomes ``size``, and rounds each side to a multiple no smaller than ``size``;
    ``upper_bound`` takes ``s = size / max(height, width)`` and rounds to a multiple no larger.
    """
    if preset.resize == "lower_bound":
        scale = max(size / height, size / width)
        bounds = {"min_val": size}
    else:
        scale = min(size / height, size / width)
        bounds = {"max_val": size}
    m = preset.multiple_of
    return (constrain_to_multiple(scale * height, m, **bounds),
            constrain_to_multiple(scale * width, m, **bounds))


def choose_providers(wanted: tuple[str, ...], available: list[str]) -> list[str]:
    """onnxruntime names of the ``wanted`` providers that are ``available``, in the order
    wanted (the preference), without repeats.

    Raises :class:`NetworkError` when none of them is available.
    """
    chosen = [PROVIDERS[name] for name in dict.fromkeys(wanted) if PROVIDERS[name] in available]
    if not chosen:
        raise NetworkError(f"none of the wanted execution providers ({', '.join(wanted)}) is "
                           f"available; this onnxruntime offers {', '.join(available)}. "
                           "Add \"cpu\" to [depth_network] providers, or install the "
                           "onnxruntime build for your GPU")
    return chosen


def provider_options(name: str, options: NetworkOptions) -> dict[str, str]:
    """onnxruntime options of the provider ``name``: TensorRT's precision and engine cache;
    the others' defaults."""
    if name != PROVIDERS["tensorrt"]:
        return {}
    settings = {"trt_fp16_enable": str(options.tensorrt_fp16)}
    if options.tensorrt_cache_dir:
        settings["trt_engine_cache_enable"] = "True"
        settings["trt_engine_cache_path"] = options.tensorrt_cache_dir
    return settings


def read_model(options: NetworkOptions) -> bytes:
    """The model file's bytes, its SHA-256 checked when ``options.sha256`` is given."""
    if not options.model:
        raise NetworkError("no depth model given: set [depth_network] model to the path of "
                           "an ONNX file")
    path = Path(options.model).expanduser()
    try:
        data = path.read_bytes()
    except OSError as error:
        raise NetworkError(f"cannot read the depth model {path}: "
                           f"{error.strerror or error}") from error
    if options.sha256:
        digest = hashlib.sha256(data).hexdigest()
        if digest != options.sha256.lower():
            raise NetworkError(f"the depth model {path} has sha256 {digest}, but [depth_network] "
                               f"sha256 expects {options.sha256.lower()}: wrong or damaged file")
    return data


def _create_session(data: bytes, options: NetworkOptions) -> onnxruntime.InferenceSession:
    """An onnxruntime session on the model bytes with the preferred available providers."""
    names = choose_providers(options.providers, onnxruntime.get_available_providers())
    session_options = onnxruntime.SessionOptions()
    if options.threads > 0:
        session_options.intra_op_num_threads = options.threads
    # Idle worker threads sleep instead of spinning: the network shares the CPU with the VINS
    # and the event loop, which a spinning pool would starve between inferences.
    session_options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    providers = [(name, provider_options(name, options)) for name in names]
    try:
        return onnxruntime.InferenceSession(data, session_options, providers=providers)
    # onnxruntime's errors (InvalidProtobuf, Fail, ...) derive from Exception directly.
    except Exception as error:
        raise NetworkError(f"onnxruntime cannot load the depth model {options.model} (is it an "
                           f"ONNX file?): {error}") from error


def _fixed_input_shape(session: onnxruntime.InferenceSession, path: str) -> tuple[int, int] | None:
    """The (h, w) the model's single image input is fixed to, or None when both are symbolic.

    Raises :class:`NetworkError` for any other interface than one (1, 3, h, w) float or float16
    tensor (a symbolic batch or channel dimension is accepted).
    """
    inputs = session.get_inputs()

    def mismatch(what: str) -> NetworkError:
        return NetworkError(f"mismatched model {path}: {what}; a depth model takes one "
                            "(1, 3, height, width) float image")

    if len(inputs) != 1:
        names = ", ".join(i.name for i in inputs)
        raise mismatch(f"it has {len(inputs)} inputs ({names})")
    tensor = inputs[0]
    if tensor.type not in ("tensor(float)", "tensor(float16)"):
        raise mismatch(f"input {tensor.name!r} is {tensor.type}")
    if len(tensor.shape) != 4:
        raise mismatch(f"input {tensor.name!r} has shape {tensor.shape}")
    batch, channels, height, width = tensor.shape
    if isinstance(batch, int) and batch != 1:
        raise mismatch(f"input {tensor.name!r} has batch size {batch}")
    if isinstance(channels, int) and channels != 3:
        raise mismatch(f"input {tensor.name!r} has {channels} channels")
    fixed = [isinstance(height, int) and height > 0, isinstance(width, int) and width > 0]
    if all(fixed):
        return height, width
    if any(fixed):
        raise mismatch(f"input {tensor.name!r} fixes only one of height and width "
                       f"{tensor.shape}")
    return None


class DepthNetwork:
    """An opened, checked depth model: camera image in, relative depth at camera size out.

    ``provider`` is the onnxruntime execution provider in use, ``preset`` the :class:`Preset`,
    ``options`` the :class:`NetworkOptions` it was opened with.
    """

    def __init__(self, session: onnxruntime.InferenceSession, options: NetworkOptions,
                 fixed_shape: tuple[int, int] | None):
        self._session = session
        self._input = session.get_inputs()[0]
        self._output = session.get_outputs()[0].name
        self._dtype = np.float16 if self._input.type == "tensor(float16)" else np.float32
        self._fixed_shape = fixed_shape
        self._size = network_input_size(options)
        self.options = options
        self.preset = PRESETS[options.preset]
        self.provider = session.get_providers()[0]
        std = np.asarray(self.preset.std, np.float32)
        self._scale = (1.0 / (255.0 * std)).astype(np.float32)
        self._shift = (-np.asarray(self.preset.mean, np.float32) / std).astype(np.float32)

    @classmethod
    def open(cls, options: NetworkOptions,
             camera_size: tuple[int, int] = (480, 640)) -> DepthNetwork:
        """Read, check and warm up the model for ``camera_size`` (height, width) images.

        Raises :class:`NetworkError` for a missing, unreadable or damaged file, an interface
        that is not one image in and one depth image out, or a failing warm-up inference.
        """
        session = _create_session(read_model(options), options)
        fixed_shape = _fixed_input_shape(session, options.model)
        network = cls(session, options, fixed_shape)
        network._log_start(camera_size)
        network._warm_up(camera_size)
        return network

    def _log_start(self, camera_size: tuple[int, int]) -> None:
        """Say which provider runs the model and at what input size."""
        log.info("depth network %s runs on %s", self.options.model, self.provider)
        wanted = PROVIDERS[self.options.providers[0]]
        if self.provider != wanted:
            log.warning("depth network runs on %s, not on the preferred %s (unavailable, or "
                        "onnxruntime fell back)", self.provider, wanted)
        if self._fixed_shape is not None:
            log.info("depth model has a fixed input of %dx%d (height x width): images are "
                     "resized to it without keeping their aspect ratio", *self._fixed_shape)
        else:
            log.info("depth network input for %dx%d images: %dx%d (%s)", *camera_size,
                     *self.input_size_for(*camera_size), self.preset.name)

    def _warm_up(self, camera_size: tuple[int, int]) -> None:
        """One inference on a mid-grey image, so a model that cannot run fails before arming."""
        image = np.full(camera_size, 128, np.uint8)
        try:
            output = self.run(self.preprocess(image))
        except NetworkError:
            raise
        except Exception as error:
            raise NetworkError(f"the depth model {self.options.model} failed its warm-up "
                               f"inference on a {camera_size[0]}x{camera_size[1]} image: "
                               f"{error}") from error
        self.postprocess(output, camera_size)

    def input_size_for(self, height: int, width: int) -> tuple[int, int]:
        """(h, w) of the network input for a ``height`` x ``width`` camera image."""
        if self._fixed_shape is not None:
            return self._fixed_shape
        return keep_aspect_size(height, width, self._size, self.preset)

    def preprocess(self, image: np.ndarray, channels: str = "bgr") -> np.ndarray:
        """The (1, 3, h, w) float32 network input of a uint8 image.

        ``image`` is grey (H, W) or colour (H, W, 3) in ``channels`` order ("bgr", OpenCV's, or
        "rgb"). Resized bicubically to :meth:`input_size_for` in float32, then per RGB channel
        ``x * 1 / (255 std) - mean / std`` = ``(x / 255 - mean) / std``.
        """
        rgb = _to_rgb(image, channels)
        h, w = self.input_size_for(*rgb.shape[:2])
        resized = cv2.resize(rgb.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
        resized *= self._scale
        resized += self._shift
        return np.ascontiguousarray(resized.transpose(2, 0, 1))[np.newaxis]

    def run(self, tensor: np.ndarray) -> np.ndarray:
        """The network's raw output for a preprocessed input, as a 2-D float32 image.

        Accepts outputs shaped (h, w), (1, h, w) or (1, 1, h, w); anything else raises
        :class:`NetworkError`.
        """
        feed = {self._input.name: tensor.astype(self._dtype, copy=False)}
        output = np.asarray(self._session.run([self._output], feed)[0])
        if (output.dtype.kind != "f" or not 2 <= output.ndim <= 4
                or any(n != 1 for n in output.shape[:-2])):
            raise NetworkError(f"mismatched model {self.options.model}: output "
                               f"{self._output!r} is {output.dtype} of shape {output.shape}; "
                               "a depth model gives one float (1, height, width) image")
        return output.reshape(output.shape[-2:]).astype(np.float32, copy=False)

    def postprocess(self, output: np.ndarray, camera_size: tuple[int, int]) -> np.ndarray:
        """The 2-D ``output`` upsampled to ``camera_size`` (height, width), float32, with the
        preset's interpolation."""
        height, width = camera_size
        if self.preset.upsample == "bilinear_align_corners":
            return resize_align_corners(output, height, width)
        return cv2.resize(output, (width, height), interpolation=cv2.INTER_CUBIC)

    def __call__(self, image: np.ndarray, channels: str = "bgr") -> np.ndarray:
        """Relative depth of a uint8 camera image at its own resolution (float32)."""
        output = self.run(self.preprocess(image, channels))
        return self.postprocess(output, image.shape[:2])


def resize_align_corners(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize with corner pixels aligned, as ``F.interpolate(..., "bilinear",
    align_corners=True)``.

    Output pixel (x, y) samples the input at ``(x (w_in - 1) / (w_out - 1),
    y (h_in - 1) / (h_out - 1))``, so the four corners are copied exactly. OpenCV quantises the
    sample positions to 1/32 pixel, so a value may differ from exact bilinear interpolation by
    at most 1/64 of the largest step between neighbouring input pixels, per axis.
    """
    h_in, w_in = image.shape
    sx = (w_in - 1) / (width - 1) if width > 1 else 0.0
    sy = (h_in - 1) / (height - 1) if height > 1 else 0.0
    matrix = np.array([[sx, 0.0, 0.0], [0.0, sy, 0.0]])
    return cv2.warpAffine(np.asarray(image, np.float32), matrix, (width, height),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def _to_rgb(image: np.ndarray, channels: str) -> np.ndarray:
    """A uint8 (H, W, 3) RGB view or copy of a grey or colour uint8 image."""
    if channels not in ("bgr", "rgb"):
        raise ValueError(f"channels must be 'bgr' or 'rgb', got {channels!r}")
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        kind = image.dtype if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"the depth network takes uint8 images, got {kind}")
    if image.size == 0:
        raise ValueError(f"the depth network got an empty image of shape {image.shape}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if channels == "bgr" else image
    raise ValueError(f"the depth network takes (H, W) grey or (H, W, 3) colour images, got "
                     f"shape {image.shape}")
