"""The camera model of issue 21, against what a user relies on: the lens models are OpenCV's
(so a calibration from OpenCV, Kalibr or a device's SDK means the same here), rectification
turns a distorted frame into the ideal pinhole image of the same scene, a Kalibr camchain lands
in the body frame and on the IMU's clock with the signs Kalibr documents, and bad input gets a
message that names what to fix.

The references are independent of our code: OpenCV's own projection and undistortion
(``cv2.projectPoints``, ``cv2.fisheye.*``, ``cv2.initUndistortRectifyMap``), and a synthetic
scene rendered both through an ideal pinhole and through the distorting lens, the distorted
image made by looking up each distorted pixel's ray with OpenCV's iterative undistortion.
"""

import asyncio
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml

from autonomy.geometry import PinholeCamera, invert_pose
from autonomy.lens import CameraModel, Rectifier
from autonomy.messages import Frame
from companion.config import ConfigError, load_config
from drivers.camera.base import CameraError
from drivers.camera.calibration import CalibratedCamera, resolve
from drivers.camera.kalibr import KalibrError, read_camchain
from drivers.camera.options import CameraOptions

#: EuRoC MAV's cam0 (sensor.yaml of the dataset: 752x480, radtan): strong barrel distortion.
EUROC = CameraModel(PinholeCamera(752, 480, 458.654, 457.296, 367.215, 248.375), "radtan",
                    (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05))
#: A RealSense T265 fisheye (848x800, Kannala-Brandt), as farm-ng/tractor copied it from a
#: T265 (modules/perception/cpp/farm_ng/perception/camera_model.cpp,
#: DefaultFishEyeT265CameraModel): about 160 degrees across, which no pinhole image holds.
T265 = CameraModel(PinholeCamera(848, 800, 286.0, 286.0, 423.5, 399.5), "equidistant",
                   (-0.0080617731437087059, 0.04318523034453392, -0.039864420890808105,
                    0.0068964879028499126))
T265_RECTIFIED_HFOV = 110.0
EXACT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


# ------------------------------------------------------------------ the lens models vs OpenCV

@pytest.mark.parametrize("coefficients", [EUROC.coefficients, EUROC.coefficients + (0.02,),
                                          (0.12, -0.3, -0.004, 0.006, 0.15)])
def test_radtan_distortion_is_opencvs(coefficients):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.0, 1.0, (2000, 2))  # normalised coordinates of a wide image's corners
    model = CameraModel(EUROC.pinhole, "radtan", coefficients)
    points = np.column_stack([xy, np.ones(len(xy))])
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), np.eye(3),
                                    np.array(coefficients))
    expected = expected.reshape(-1, 2)
    ours = model.distort(xy)
    assert np.all(np.abs(ours - expected) <= 1e-9 * np.abs(expected) + 1e-15)
    assert np.abs(ours - xy).max() > 0.1  # the distortion is strong here, not a no-op


@pytest.mark.parametrize("coefficients", [T265.coefficients, (-0.01, 0.05, -0.07, 0.03)])
def test_equidistant_distortion_is_opencvs_fisheye(coefficients):
    rng = np.random.default_rng(2)
    # rays up to about 80 degrees off the axis, and the axis itself (r = 0, the limit)
    xy = np.vstack([rng.uniform(-4.0, 4.0, (2000, 2)), [[0.0, 0.0], [1e-9, 0.0]]])
    model = CameraModel(T265.pinhole, "equidistant", coefficients)
    D = np.array(coefficients)
    ours = model.distort(xy)
    projected, _ = cv2.fisheye.projectPoints(np.column_stack([xy, np.ones(len(xy))])[:, None],
                                             np.zeros(3), np.zeros(3), np.eye(3), D)
    distorted = cv2.fisheye.distortPoints(xy[:, None], np.eye(3), D)
    for expected in (projected.reshape(-1, 2), distorted.reshape(-1, 2)):
        assert np.all(np.abs(ours - expected) <= 1e-9 * np.abs(expected) + 1e-15)
    assert np.array_equal(ours[-2], [0.0, 0.0])


def test_no_distortion_changes_nothing():
    model = CameraModel(EUROC.pinhole)
    xy = np.random.default_rng(3).normal(size=(50, 2))
    assert np.array_equal(model.distort(xy), xy)
    assert model.is_pinhole and CameraModel(EUROC.pinhole, "radtan", (0, 0, 0, 0)).is_pinhole
    assert not EUROC.is_pinhole and not T265.is_pinhole


def test_an_equidistant_lens_with_zero_coefficients_is_still_a_fisheye():
    """k = 0 is the ideal equidistant lens r = f theta: its frames need resampling onto the
    pinhole r = f tan(theta), exactly as OpenCV's fisheye maps do."""
    ideal_fisheye = CameraModel(T265.pinhole, "equidistant", (0.0, 0.0, 0.0, 0.0))
    assert not ideal_fisheye.is_pinhole
    calibration = resolve(CameraOptions(width=848, height=480, fx=286.0, cx=423.5, cy=239.5,
                                        distortion_model="equidistant",
                                        distortion=(0.0, 0.0, 0.0, 0.0)))
    camera = CalibratedCamera(FakeCamera([Frame(1.0, coordinate_image(848, 480))]), calibration)
    rectified = asyncio.run(camera.next_frame()).image
    K = calibration.model.pinhole.K
    mx, my = cv2.fisheye.initUndistortRectifyMap(K, np.zeros(4), np.eye(3), K, (848, 480),
                                                 cv2.CV_32FC1)
    inside = (mx > 1) & (mx < 846) & (my > 1) & (my < 478)
    assert inside.mean() > 0.9
    assert np.abs(rectified[..., 0] - mx)[inside].max() < 0.05
    assert np.abs(rectified[..., 1] - my)[inside].max() < 0.05


# ------------------------------------------------------------------ rectification

def coordinate_image(width: int, height: int) -> np.ndarray:
    """A float32 image whose channels are each pixel's own (u, v, 0): bilinear resampling of
    it gives back, at each output pixel, the source coordinates it was taken from."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    return np.dstack([u, v, np.zeros_like(u)])


def opencv_maps(model: CameraModel, target: PinholeCamera):
    K, D, size = model.pinhole.K, np.array(model.coefficients), (target.width, target.height)
    if model.distortion == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), target.K, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K, D, None, target.K, size, cv2.CV_32FC1)


def inside(mx: np.ndarray, my: np.ndarray, model: CameraModel) -> np.ndarray:
    """Target pixels whose source lies a pixel or more inside the source image."""
    p = model.pinhole
    return (mx >= 1) & (mx <= p.width - 2) & (my >= 1) & (my <= p.height - 2)


@pytest.mark.parametrize("model, hfov", [(EUROC, 0.0), (T265, T265_RECTIFIED_HFOV)],
                         ids=["radtan", "equidistant"])
def test_rectifier_maps_are_opencvs(model, hfov):
    target = model.rectified(hfov)
    rectifier = Rectifier(model, target)
    p = model.pinhole
    taken_from = rectifier(coordinate_image(p.width, p.height))
    mx, my = opencv_maps(model, target)
    keep = inside(mx, my, model)
    assert keep.mean() > 0.95
    assert np.abs(taken_from[..., 0] - mx)[keep].max() < 0.05
    assert np.abs(taken_from[..., 1] - my)[keep].max() < 0.05


class Scene:
    """A textured sphere around the camera: RGB as a smooth random function of a ray's
    direction (six plane waves per channel, angular wavelengths 0.08-0.15 rad, so about 25-45
    pixels of these lenses: detail a lens error of a few pixels visibly moves, and smooth
    enough for bilinear resampling)."""

    def __init__(self, seed: int = 3):
        rng = np.random.default_rng(seed)
        waves = rng.normal(size=(3, 6, 3))
        waves /= np.linalg.norm(waves, axis=-1, keepdims=True)
        self.waves = waves * 2 * np.pi / rng.uniform(0.08, 0.15, size=(3, 6, 1))
        self.phases = rng.uniform(0, 2 * np.pi, (3, 6))

    def colour(self, xy: np.ndarray) -> np.ndarray:
        """Float RGB (N, 3) seen along the rays through normalised coordinates ``xy``."""
        d = np.column_stack([xy, np.ones(len(xy))])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.stack([128.0 + 15.0 * np.sin(d @ self.waves[c].T + self.phases[c]).sum(1)
                         for c in range(3)], axis=1)

    def pinhole_image(self, camera: PinholeCamera) -> np.ndarray:
        """The float image an ideal pinhole ``camera`` sees."""
        xy = camera.rays()[..., :2].reshape(-1, 2)
        return self.colour(xy).reshape(camera.height, camera.width, 3)

    def lens_image(self, model: CameraModel) -> np.ndarray:
        """The uint8 frame the distorting lens ``model`` delivers: each pixel's ray from
        OpenCV's undistortion, checked by distorting it back (pixels whose ray is not found,
        beyond a fisheye's 90 degrees, stay black)."""
        p, D = model.pinhole, np.array(model.coefficients)
        u, v = np.meshgrid(np.arange(p.width, dtype=float), np.arange(p.height, dtype=float))
        pixels = np.column_stack([u.ravel(), v.ravel()])[:, None]
        if model.distortion == "equidistant":
            xy = cv2.fisheye.undistortPoints(pixels, p.K, D, None, np.eye(3), np.eye(3), EXACT)
            back = cv2.fisheye.distortPoints(xy, p.K, D)
        else:
            xy = cv2.undistortPoints(pixels, p.K, D, None, None, None, EXACT)
            back, _ = cv2.projectPoints(np.dstack([xy, np.ones(xy.shape[:2])]), np.zeros(3),
                                        np.zeros(3), p.K, D)
        xy = xy.reshape(-1, 2)
        found = np.linalg.norm((back - pixels).reshape(-1, 2), axis=1) < 1e-3
        image = np.where(found[:, None], self.colour(xy), 0.0)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8).reshape(p.height, p.width, 3)


SCENE = Scene()


@pytest.fixture(scope="module")
def lens_images():
    return {"radtan": SCENE.lens_image(EUROC), "equidistant": SCENE.lens_image(T265)}


@pytest.mark.parametrize("model, hfov", [(EUROC, 0.0), (T265, T265_RECTIFIED_HFOV)],
                         ids=["radtan", "equidistant"])
def test_rectified_frame_is_the_ideal_pinhole_image(model, hfov, lens_images):
    frame = lens_images[model.distortion]
    target = model.rectified(hfov)
    rectified = Rectifier(model, target)(frame)
    assert rectified.shape == (target.height, target.width, 3) and rectified.dtype == np.uint8
    ideal = SCENE.pinhole_image(target)
    keep = inside(*opencv_maps(model, target), model)
    keep[:4], keep[-4:], keep[:, :4], keep[:, -4:] = False, False, False, False
    error = np.abs(rectified - ideal).mean(axis=2)[keep]
    # uint8 rounding of the frame alone costs 0.25 on average
    assert error.mean() < 0.6 and np.percentile(error, 99) < 2.0
    # the test can tell: taking the lens for a pinhole of the same intrinsics is far off
    as_pinhole = Rectifier(CameraModel(model.pinhole), target)(frame)
    assert np.abs(as_pinhole - ideal).mean(axis=2)[keep].mean() > 10 * error.mean()


def test_rays_that_miss_the_frame_come_out_black():
    model = CameraModel(PinholeCamera(64, 48, 40.0, 40.0, 31.5, 23.5))
    wider = model.rectified(120.0)  # sees more than the source image holds
    out = Rectifier(model, wider)(np.full((48, 64, 3), 200, np.uint8))
    assert (out[0, 0] == 0).all() and (out[-1, -1] == 0).all()
    assert (out[24, 32] == 200).all()
    assert not out.flags.writeable


def test_rectifier_rejects_a_frame_of_another_size():
    rectifier = Rectifier(EUROC, EUROC.rectified())
    with pytest.raises(ValueError, match="image is 640x480, the camera model is 752x480"):
        rectifier(np.zeros((480, 640, 3), np.uint8))


def test_rectified_pinhole_spans_the_asked_field_of_view():
    assert EUROC.rectified() == EUROC.pinhole
    wide = T265.rectified(90.0)
    assert (wide.fx, wide.fy, wide.cx, wide.cy) == pytest.approx((424.0, 424.0, 423.5, 399.5))
    assert (wide.width, wide.height) == (848, 800)
    for hfov in (180.0, 200.0, float("nan")):
        with pytest.raises(ValueError, match="less than 180 degrees"):
            T265.rectified(hfov)


# ------------------------------------------------------------------ bad lens input

@pytest.mark.parametrize("distortion, coefficients, message", [
    ("kannala_brandt", (0.1, 0.0, 0.0, 0.0),
     "unknown distortion model 'kannala_brandt'; expected one of none, radtan, equidistant"),
    ("radtan", (0.1, 0.0, 0.0), "radtan distortion takes 4 or 5 coefficients, got 3"),
    ("radtan", (0.1,) * 6, "radtan distortion takes 4 or 5 coefficients, got 6"),
    ("equidistant", (0.1, 0.0, 0.0, 0.0, 0.0), "equidistant distortion takes 4 coefficients, "
                                               "got 5"),
    ("none", (0.1, 0.0, 0.0, 0.0), "none distortion takes 0 coefficients, got 4"),
    ("radtan", (0.1, float("nan"), 0.0, 0.0), "distortion coefficients must be finite"),
    ("equidistant", (0.1, 0.0, float("inf"), 0.0), "distortion coefficients must be finite"),
])
def test_camera_model_rejects_bad_lenses(distortion, coefficients, message):
    with pytest.raises(ValueError) as error:
        CameraModel(EUROC.pinhole, distortion, coefficients)
    assert message in str(error.value)


# ------------------------------------------------------------------ Kalibr camchains

#: The example camchain of Kalibr's documentation (github.com/ethz-asl/kalibr/wiki/yaml-formats,
#: "Example chain.yaml"), cam1 without its T_cn_cnm1: a 752x480 camera whose optical axis is
#: the IMU's z axis, and an omnidirectional second camera.
KALIBR_WIKI = """\
cam0:
  camera_model: pinhole
  intrinsics: [461.629, 460.152, 362.680, 246.049]
  distortion_model: radtan
  distortion_coeffs: [-0.27695497, 0.06712482, 0.00087538, 0.00011556]
  T_cam_imu:
  - [0.01779318, 0.99967549,-0.01822936, 0.07008565]
  - [-0.9998017, 0.01795239, 0.00860714,-0.01771023]
  - [0.00893160, 0.01807260, 0.99979678, 0.00399246]
  - [0.0, 0.0, 0.0, 1.0]
  timeshift_cam_imu: -8.121e-05
  rostopic: /cam0/image_raw
  resolution: [752, 480]
cam1:
  camera_model: omni
  intrinsics: [0.80065662, 833.006, 830.345, 373.850, 253.749]
  distortion_model: radtan
  distortion_coeffs: [-0.33518750, 0.13211436, 0.00055967, 0.00057686]
  rostopic: /cam1/image_raw
  resolution: [752, 480]
"""


def camchain(T_cam_imu, *, shift=0.004, model="equidistant",
             coefficients=T265.coefficients) -> str:
    """The camchain Kalibr writes for a T265-like fisheye with the extrinsics ``T_cam_imu``."""
    return yaml.safe_dump({"cam0": {
        "T_cam_imu": np.asarray(T_cam_imu, float).tolist(), "cam_overlaps": [],
        "camera_model": "pinhole", "distortion_coeffs": list(coefficients),
        "distortion_model": model, "intrinsics": [286.0, 286.0, 423.5, 399.5],
        "resolution": [848, 800], "rostopic": "/camera/fisheye1/image_raw",
        "timeshift_cam_imu": shift}})


def forward_camera_T_cam_imu(R_imu_flu: np.ndarray) -> np.ndarray:
    """Kalibr's ``T_cam_imu`` for a camera looking straight ahead, 12 cm ahead of and 3 cm
    above the IMU, when the IMU's axes are ``R_imu_flu`` applied to the body's FLU axes."""
    R_flu_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # x right...
    T_imu_cam = np.eye(4)
    T_imu_cam[:3, :3] = R_imu_flu @ R_flu_cam
    T_imu_cam[:3, 3] = R_imu_flu @ np.array([0.12, 0.0, 0.03])
    return invert_pose(T_imu_cam)


def write(tmp_path, text, name="camchain-imucam.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_kalibr_documentation_example_reads_as_written(tmp_path):
    path = write(tmp_path, KALIBR_WIKI)
    cam = read_camchain(path)
    p = cam.model.pinhole
    assert (p.width, p.height, p.fx, p.fy, p.cx, p.cy) == (752, 480, 461.629, 460.152,
                                                           362.680, 246.049)
    assert cam.model.distortion == "radtan"
    assert cam.model.coefficients == (-0.27695497, 0.06712482, 0.00087538, 0.00011556)
    assert cam.time_offset_s == -8.121e-05
    # Kalibr's T_cam_imu takes IMU points into the camera; T_B_C takes camera points into
    # the body (= the FLU IMU here), so the two undo each other on any point
    T_cam_imu = np.array(yaml.safe_load(KALIBR_WIKI)["cam0"]["T_cam_imu"])
    points_B = np.random.default_rng(4).normal(size=(4, 10))
    points_B[3] = 1.0
    assert np.allclose(cam.T_B_C @ (T_cam_imu @ points_B), points_B, atol=1e-6)
    assert np.allclose(cam.T_B_C[3], [0, 0, 0, 1])


def test_kalibr_forward_camera_looks_along_the_body_x_axis(tmp_path):
    flu = read_camchain(write(tmp_path, camchain(forward_camera_T_cam_imu(np.eye(3)))))
    R, t = flu.T_B_C[:3, :3], flu.T_B_C[:3, 3]
    assert np.allclose(R[:, 2], [1, 0, 0])   # optical axis (z) forward
    assert np.allclose(R[:, 0], [0, -1, 0])  # image x to the right
    assert np.allclose(R[:, 1], [0, 0, -1])  # image y down
    assert np.allclose(t, [0.12, 0.0, 0.03])
    # the same mounting written in the config's own words gives the same pose
    assert np.allclose(flu.T_B_C, CameraOptions(mount_x=0.12, mount_z=0.03).T_B_C())
    assert flu.model == T265


def test_kalibr_with_px4s_frd_imu_gives_the_same_body_pose(tmp_path):
    """Kalibr given PX4's FRD IMU writes a different T_cam_imu for the same camera; with
    imu_frame "frd" it lands on the same FLU body pose, and read as "flu" its y and z flip."""
    frd = np.diag([1.0, -1.0, -1.0])
    path = write(tmp_path, camchain(forward_camera_T_cam_imu(frd)))
    truth = read_camchain(write(tmp_path, camchain(forward_camera_T_cam_imu(np.eye(3))),
                                "flu.yaml"))
    as_frd = read_camchain(path, imu_frame="frd")
    assert np.allclose(as_frd.T_B_C, truth.T_B_C)
    as_flu = read_camchain(path, imu_frame="flu")
    assert np.allclose(as_flu.T_B_C[:3, 3], [0.12, 0.0, -0.03])
    assert np.allclose(as_flu.T_B_C[:3, :3], frd @ truth.T_B_C[:3, :3])


def test_kalibr_timeshift_puts_frames_on_the_imu_clock(tmp_path):
    """Kalibr: t_imu = t_cam + timeshift_cam_imu. A frame taken at camera time 10.0 is the
    IMU's 10.004, and that is the time the stack must see."""
    path = write(tmp_path, camchain(forward_camera_T_cam_imu(np.eye(3)), shift=0.004))
    options = CameraOptions(width=848, height=800, calibration="kalibr", kalibr_file=str(path),
                            rectified_hfov_deg=T265_RECTIFIED_HFOV, time_offset_s=-0.2,
                            mount_x=1.0)
    calibration = resolve(options)
    assert calibration.time_offset_s == 0.004  # the file's, not the config's time_offset_s
    assert np.allclose(calibration.T_B_C[:3, 3], [0.12, 0.0, 0.03])  # nor its mount_*
    assert calibration.model == T265 and str(path) in calibration.source
    assert calibration.rectified == T265.rectified(T265_RECTIFIED_HFOV)
    camera = CalibratedCamera(FakeCamera([Frame(10.0, np.zeros((800, 848, 3), np.uint8))]),
                              calibration)
    frame = asyncio.run(camera.next_frame())
    assert frame.t == 10.0 + 0.004


BAD_CAMCHAINS = {
    "not YAML": ("cam0: {intrinsics: [1, 2\n", "not YAML"),
    "empty": ("", "not a Kalibr camchain"),
    "a list": ("- cam0\n- cam1\n", "not a Kalibr camchain"),
    "no such camera": (KALIBR_WIKI.replace("cam0:", "cam7:"),
                       "no camera 'cam0'; it has cam7, cam1"),
    "omni": (KALIBR_WIKI.replace("cam0:", "camX:").replace("cam1:", "cam0:"),
             "camera_model 'omni' is not supported"),
    "not rigid": (KALIBR_WIKI.replace("[0.01779318, 0.99967549", "[0.5, 0.99967549"),
                  "T_cam_imu is not a rigid transform"),
    "mirrored": (KALIBR_WIKI.replace("[0.00893160, 0.01807260, 0.99979678",
                                     "[-0.00893160, -0.01807260, -0.99979678"),
                 "T_cam_imu is not a rigid transform"),
    "no T_cam_imu (a camchain.yaml)": (
        KALIBR_WIKI.replace("  T_cam_imu:\n", "  T_bogus:\n"), "T_cam_imu must be a 4x4 matrix"),
    "3 intrinsics": (KALIBR_WIKI.replace("[461.629, 460.152, 362.680, 246.049]",
                                         "[461.629, 460.152, 362.680]"),
                     "intrinsics must be a list of 4 numbers"),
    "text intrinsics": (KALIBR_WIKI.replace("461.629", "fu"), "intrinsics must hold finite"),
    "no resolution": (KALIBR_WIKI.replace("  resolution: [752, 480]\ncam1", "cam1"),
                      "resolution must be a list of 2 numbers"),
    "text distortion": (KALIBR_WIKI.replace("0.00087538", "small"),
                        "distortion_coeffs must hold finite numbers, got 'small'"),
    "empty distortion_coeffs": (KALIBR_WIKI.replace(
        "[-0.27695497, 0.06712482, 0.00087538, 0.00011556]", ""),
        "distortion_coeffs must be a list of numbers, got None"),
    "fov lens": (KALIBR_WIKI.replace("distortion_model: radtan", "distortion_model: fov", 1),
                 "unknown distortion model 'fov'"),
    "5 equidistant coefficients": (
        KALIBR_WIKI.replace("distortion_model: radtan", "distortion_model: equidistant", 1)
        .replace("0.00011556]", "0.00011556, 0.1]"), "equidistant distortion takes 4"),
    "text timeshift": (KALIBR_WIKI.replace("-8.121e-05", "soon"), "timeshift_cam_imu must hold"),
}


@pytest.mark.parametrize("case", list(BAD_CAMCHAINS))
def test_kalibr_rejects_what_the_stack_cannot_use(tmp_path, case):
    text, message = BAD_CAMCHAINS[case]
    path = write(tmp_path, text)
    with pytest.raises(KalibrError) as error:
        read_camchain(path)
    assert str(error.value).startswith(f"{path}: ")
    assert message in str(error.value)
    assert str(error.value).count(str(path)) == 1  # said once, not once per layer


def test_kalibr_missing_or_binary_file_or_bad_imu_frame(tmp_path):
    with pytest.raises(KalibrError, match="nothing.yaml: cannot read it: No such file"):
        read_camchain(tmp_path / "nothing.yaml")
    report = tmp_path / "report-imucam.pdf"  # Kalibr writes it beside the camchain
    report.write_bytes(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n1 0 obj\n")
    with pytest.raises(KalibrError, match="report-imucam.pdf: not YAML"):
        read_camchain(report)
    with pytest.raises(KalibrError, match="IMU frame must be one of flu, frd, got 'ned'"):
        read_camchain(write(tmp_path, KALIBR_WIKI), imu_frame="ned")


# ------------------------------------------------------------------ options and resolve

class FakeCamera:
    """Our camera-driver interface, as the stack calls it: ``await next_frame()``, plus the
    attributes a driver carries."""

    name = "fake0"

    def __init__(self, frames):
        self.frames = list(frames)
        self.dropped = 3

    async def next_frame(self) -> Frame:
        return self.frames.pop(0)


def test_default_camera_passes_frames_through_unchanged():
    options = CameraOptions()
    calibration = resolve(options)
    assert calibration.model == CameraModel(options.pinhole())
    assert calibration.rectified == options.pinhole()
    assert np.array_equal(calibration.T_B_C, options.T_B_C())
    assert calibration.time_offset_s == 0.0 and calibration.source == "config"
    image = np.random.default_rng(5).integers(0, 256, (480, 640, 3), np.uint8)
    depth = np.full((480, 640), 2.0, np.float32)
    camera = CalibratedCamera(FakeCamera([Frame(1.5, image, depth)]), calibration)
    frame = asyncio.run(camera.next_frame())
    assert frame.t == 1.5 and np.array_equal(frame.image, image) and frame.truth_depth is depth


def test_config_radtan_lens_frames_come_rectified(lens_images):
    p = EUROC.pinhole
    options = CameraOptions(width=p.width, height=p.height, fx=p.fx, fy=p.fy, cx=p.cx, cy=p.cy,
                            distortion_model="radtan", distortion=EUROC.coefficients,
                            time_offset_s=-0.012)
    calibration = resolve(options)
    assert calibration.model == EUROC and calibration.rectified == EUROC.pinhole
    driver = FakeCamera([Frame(2.0, lens_images["radtan"])])
    camera = CalibratedCamera(driver, calibration)
    frame = asyncio.run(camera.next_frame())
    assert frame.t == pytest.approx(2.0 - 0.012, abs=1e-15)
    assert np.array_equal(frame.image, Rectifier(EUROC, EUROC.pinhole)(lens_images["radtan"]))
    error = np.abs(frame.image - SCENE.pinhole_image(EUROC.pinhole)).mean(axis=2)[4:-4, 4:-4]
    assert error.mean() < 0.6
    # everything else is the driver's
    assert camera.name == "fake0" and camera.dropped == 3
    driver.dropped = 7
    assert camera.dropped == 7
    with pytest.raises(AttributeError):
        camera.no_such_attribute


def test_a_simulated_cameras_true_depth_is_rectified_with_its_image():
    """The simulator's true depth is aligned with the distorted image; rectified, it must stay
    aligned with the rectified image (nearest pixel: depths are never blended), NaN where the
    rectified view looks outside the lens's."""
    p = EUROC.pinhole
    depth = np.where(np.arange(p.width) < p.cx, 2.0, 5.0).astype(np.float32)
    depth = np.broadcast_to(depth, (p.height, p.width)).copy()
    calibration = resolve(CameraOptions(width=p.width, height=p.height, fx=p.fx, fy=p.fy,
                                        cx=p.cx, cy=p.cy, distortion_model="radtan",
                                        distortion=EUROC.coefficients))
    camera = CalibratedCamera(FakeCamera([Frame(0.0, np.zeros((p.height, p.width, 3), np.uint8),
                                                 depth)]),
                              calibration)
    truth = asyncio.run(camera.next_frame()).truth_depth
    assert set(np.unique(truth[np.isfinite(truth)])) == {2.0, 5.0}
    # a rectified pixel's depth is the one at the distorted pixel its ray passes through
    rays = p.rays()[..., :2].reshape(-1, 2)
    u = (p.fx * EUROC.distort(rays)[:, 0] + p.cx).reshape(p.height, p.width)
    inside = (u > 0.5) & (u < p.width - 1.5) & (np.abs(u - p.cx) > 0.6)
    assert np.array_equal(truth[inside], np.where(u[inside] < p.cx, 2.0, 5.0))


def test_narrower_rectified_view_of_an_undistorted_camera_zooms_in():
    """No lens distortion but ``rectified_hfov_deg`` set: the frames are resampled onto the
    narrower pinhole the stack is told about, not passed through under the wrong intrinsics."""
    options = CameraOptions(width=64, height=48, hfov_deg=90.0, rectified_hfov_deg=60.0)
    calibration = resolve(options)
    source, target = options.pinhole(), calibration.rectified
    assert target.fx == pytest.approx(32.0 / math.tan(math.radians(30.0)))
    camera = CalibratedCamera(FakeCamera([Frame(0.0, coordinate_image(64, 48))]), calibration)
    taken_from = asyncio.run(camera.next_frame()).image
    u, v = np.meshgrid(np.arange(64.0), np.arange(48.0))
    assert np.allclose(taken_from[..., 0], source.fx * (u - target.cx) / target.fx + source.cx,
                       atol=0.05)
    assert np.allclose(taken_from[..., 1], source.fy * (v - target.cy) / target.fy + source.cy,
                       atol=0.05)


def test_device_calibration_needs_a_device_that_has_one():
    with pytest.raises(CameraError, match="the v4l2 camera carries no calibration; set "
                                          r"\[camera\] calibration = config"):
        resolve(CameraOptions(calibration="device"))
    device = CameraModel(PinholeCamera(640, 480, 390.0, 390.0, 321.0, 238.0), "radtan",
                         (-0.055, 0.065, -0.0006, 0.0007, -0.021))
    calibration = resolve(CameraOptions(driver="realsense", calibration="device",
                                        time_offset_s=0.01), device)
    assert calibration.model == device and calibration.time_offset_s == 0.01
    assert calibration.source == "device (realsense)"
    with pytest.raises(CameraError, match=r"is for 640x480 images, \[camera\] asks for 848x800"):
        resolve(CameraOptions(calibration="device", width=848, height=800), device)


def test_kalibr_calibration_of_another_size_or_missing_file(tmp_path):
    path = write(tmp_path, KALIBR_WIKI)
    with pytest.raises(CameraError, match=r"kalibr .* is for 752x480 images, \[camera\] asks "
                                          "for 640x480"):
        resolve(CameraOptions(calibration="kalibr", kalibr_file=str(path)))
    with pytest.raises(CameraError, match=r"\[camera\] kalibr_file: .*gone.yaml: cannot read"):
        resolve(CameraOptions(calibration="kalibr", kalibr_file=str(tmp_path / "gone.yaml")))
    with pytest.raises(CameraError, match="camera_model 'omni' is not supported"):
        resolve(CameraOptions(calibration="kalibr", kalibr_file=str(path), kalibr_camera="cam1",
                              width=752, height=480))


def test_lens_keys_load_from_the_config_and_overrides(tmp_path):
    config = load_config(None, ["camera.distortion_model=radtan",
                                "camera.distortion=[0.1,0,0,0]"])
    assert config.camera.distortion == (0.1, 0.0, 0.0, 0.0)
    assert resolve(config.camera).model.coefficients == (0.1, 0.0, 0.0, 0.0)
    toml = tmp_path / "t265.toml"
    toml.write_text('[camera]\nwidth = 848\nheight = 800\nfx = 286\ncx = 423.5\ncy = 399.5\n'
                    'distortion_model = "equidistant"\n'
                    f'distortion = {list(T265.coefficients)}\nrectified_hfov_deg = 110\n')
    calibration = resolve(load_config(toml).camera)
    assert calibration.model == T265 and calibration.rectified == T265.rectified(110.0)
    kalibr = load_config(None, ["camera.calibration=kalibr", "camera.kalibr_file=/etc/cc.yaml",
                                "camera.kalibr_camera=cam1", "camera.kalibr_imu_frame=frd"])
    assert (kalibr.camera.kalibr_file, kalibr.camera.kalibr_camera,
            kalibr.camera.kalibr_imu_frame) == ("/etc/cc.yaml", "cam1", "frd")


@pytest.mark.parametrize("overrides, key, message", [
    (["camera.distortion_model=radtan", "camera.distortion=[0.1,0,0]"], "camera.distortion",
     "radtan distortion takes 4 or 5 coefficients, got 3"),
    (["camera.distortion=[0.1,0,0,0]"], "camera.distortion",
     "none distortion takes 0 coefficients, got 4"),
    (["camera.distortion_model=equidistant", "camera.distortion=[0.1,0,nan,0]"],
     "camera.distortion", "must be finite"),
    (["camera.distortion_model=fisheye"], "camera.distortion_model", "fisheye"),
    (["camera.calibration=kalibr"], "camera.kalibr_file", "camchain-imucam.yaml"),
    (["camera.kalibr_imu_frame=ned"], "camera.kalibr_imu_frame", "ned"),
    (["camera.rectified_hfov_deg=180"], "camera.rectified_hfov_deg", "180"),
])
def test_bad_lens_keys_name_the_key(overrides, key, message):
    with pytest.raises(ConfigError) as error:
        load_config(None, overrides)
    assert error.value.key == key
    assert message in str(error.value)
    assert error.value.source.startswith("--set camera.")


def test_bad_lens_keys_in_a_file_name_the_file(tmp_path):
    toml = tmp_path / "bad.toml"
    toml.write_text('[camera]\ndistortion_model = "radtan"\ndistortion = [0.1, 0.0]\n')
    with pytest.raises(ConfigError, match=r"bad.toml: camera.distortion: radtan distortion "
                                          "takes 4 or 5 coefficients, got 2"):
        load_config(toml)
    # the file's lens fixed on the command line
    fixed = load_config(toml, ["camera.distortion=[0.1, 0.0, 0.0, 0.0, 0.01]"])
    assert fixed.camera.distortion == (0.1, 0.0, 0.0, 0.0, 0.01)
    assert replace(fixed.camera, distortion_model="none", distortion=()).model().is_pinhole
