"""The recorder's topics (issue 22): each message kind encoded as its schema says, decoded
back with Foxglove's compiled protobuf classes or as JSON, the values a viewer or a replay
relies on intact."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from autonomy.geometry import PinholeCamera, make_pose, rot_z
from autonomy.messages import DepthDiagnostics, FitSamples, Frame, MetricDepth
from autonomy.navigation.mission import FlightState, Transition
from autonomy.planning.planner import Planner, PlannerOptions
from companion.recording import topics
from drivers.camera.options import CameraOptions

PINHOLE = PinholeCamera(64, 48, 40.0, 40.0, 31.5, 23.5)


def decoded(kind, data: bytes):
    message = kind()
    message.ParseFromString(data)
    return message


def metric_depth(depth: np.ndarray) -> MetricDepth:
    fit = FitSamples(np.array([0.2, 0.5]), np.array([4.0, 1.5]), np.linspace(0.2, 0.5, 4),
                     np.linspace(0.25, 0.66, 4))
    return MetricDepth(2.5, depth, np.full(depth.shape, 0.8, np.float32), held=False,
                       diagnostics=DepthDiagnostics(12, 10, 0.01, "pchip", 0.0),
                       relative=np.ones(depth.shape, np.float32), fit=fit)


def test_the_camera_image_is_a_jpeg_of_the_frame_in_its_colours():
    image = np.zeros((48, 64, 3), np.uint8)
    image[..., 0] = 200  # red in RGB
    message = decoded(CompressedImage, topics.encode_image(Frame(1.25, image), "jpeg", 95))
    assert message.format == "jpeg" and message.frame_id == topics.CAMERA
    assert (message.timestamp.seconds, message.timestamp.nanos) == (1, 250_000_000)
    bgr = cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_COLOR)
    assert abs(int(bgr[..., 2].mean()) - 200) <= 2 and bgr[..., 0].mean() < 3


def test_metric_depth_is_millimetres_with_zero_where_unknown():
    depth = np.full((48, 64), 2.5, np.float32)
    depth[0, 0] = np.nan
    depth[0, 4] = 100.0  # beyond 16 bits of millimetres: the largest it can say
    message = decoded(RawImage, topics.encode_metric(1.0, depth))
    image = np.frombuffer(message.data, np.uint16).reshape(message.height, message.width)
    assert message.encoding == "16UC1" and image.shape == (12, 16)
    assert image[0, 0] == 0 and image[0, 1] == topics.MAX_DEPTH_MM and image[1, 1] == 2500


def test_the_depth_cloud_puts_each_known_pixel_on_its_ray():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[:16] = np.nan  # the top third unknown: left out
    message = decoded(PointCloud, topics.encode_depth_points(metric_depth(depth), PINHOLE))
    names = [f.name for f in message.fields]
    points = np.frombuffer(message.data, np.float32).reshape(-1, len(names))
    assert names == ["x", "y", "z", "confidence"] and len(points) == 8  # 2 rows of 4
    x, y, z, confidence = points.T
    assert np.allclose(z, 2.0) and np.allclose(confidence, 0.8)
    rows, columns = np.array([16, 16, 16, 16, 32, 32, 32, 32]), np.tile([0, 16, 32, 48], 2)
    assert np.allclose(y, (rows - PINHOLE.cy) / PINHOLE.fy * 2.0)
    assert np.allclose(x, (columns - PINHOLE.cx) / PINHOLE.fx * 2.0)


def test_the_fit_record_has_its_anchors_and_curve_and_no_nan_in_json():
    record = json.loads(topics.encode_depth_fit(metric_depth(np.ones((48, 64), np.float32))))
    assert record["anchor_depth"] == [4.0, 1.5] and len(record["curve_relative"]) == 4
    no_fit = MetricDepth(3.0, None, None, held=False,
                         diagnostics=DepthDiagnostics(2, 0, math.nan, "", math.nan, "too few"))
    record = json.loads(topics.encode_depth_fit(no_fit))
    assert record["ok"] is False and record["residual_rms"] is None
    assert record["reason"] == "too few" and "anchor_depth" not in record


def test_a_transform_carries_the_pose():
    T = make_pose(rot_z(math.pi / 2), np.array([1.0, 2.0, 3.0]))
    message = decoded(FrameTransform, topics.encode_transform(0.5, "world", "body", T))
    assert (message.translation.x, message.translation.y, message.translation.z) == (1, 2, 3)
    assert math.isclose(message.rotation.z, math.sqrt(0.5)) \
        and math.isclose(message.rotation.w, math.sqrt(0.5))


def test_a_plan_records_its_choice_and_draws_every_candidate():
    planner = Planner(PINHOLE, PlannerOptions())
    T_B_C = CameraOptions().T_B_C()  # the body at the origin, facing x
    planner.add_depth(metric_depth(np.full((48, 64), 30.0, np.float32)), T_B_C)
    plan = planner.plan(2.5, np.eye(4), np.zeros(3), np.array([10.0, 0.0, 0.0]))
    record = json.loads(topics.encode_plan(plan))
    assert record["kind"] == "arc" and record["safe"][record["chosen"]]
    assert record["radius"] == planner.options.robot_radius  # the sphere it was checked with
    assert record["faster"] == []  # the fastest tier flown: none had nothing safe
    scene = decoded(SceneUpdate, topics.encode_plan_lines(plan))
    lines = scene.entities[0].lines
    assert len(lines) == len(plan.candidates.primitives)
    chosen = lines[record["chosen"]]
    assert [line.color.g for line in lines].count(chosen.color.g) == 1  # green alone
    assert chosen.points[0].x == 0.0  # from the start pose


def test_a_stop_for_want_of_a_safe_primitive_records_why_each_was_unsafe():
    """A wall 2 m ahead (the robot's sphere a step ahead is still clear of it: not hemmed in):
    the record carries the slowest tier's verdicts, the arcs into the wall blocked, the turns
    out of view unknown, so a failure can be explained from it."""
    planner = Planner(PINHOLE, PlannerOptions())
    planner.add_depth(metric_depth(np.full((48, 64), 2.0, np.float32)), CameraOptions().T_B_C())
    plan = planner.plan(2.5, np.eye(4), np.zeros(3), np.array([10.0, 0.0, 0.0]))
    record = json.loads(topics.encode_plan(plan))
    assert (record["kind"], record["reason"], record["chosen"]) == ("stop", "no safe primitive",
                                                                   -1)
    assert not any(record["safe"]) and 0 < sum(record["blocked"]) < len(record["blocked"])
    # and each faster tier's arcs: blocked by the wall, or meeting only unseen space
    assert [tier["speed"] for tier in record["faster"]] == [2.0, 1.0]
    assert all(tier["blocked"] > 0 and tier["blocked"] + tier["unseen"] == len(record["safe"])
               for tier in record["faster"])
    lines = decoded(SceneUpdate, topics.encode_plan_lines(plan)).entities[0].lines
    assert len(lines) == len(record["safe"]) + 1  # every candidate red, then the stop green
    assert lines[-1].color.g > 0.5 and all(line.color.g < 0.5 for line in lines[:-1])


def test_a_failsafe_transition_is_a_warning_and_a_normal_one_information():
    failsafe = Transition(4.0, FlightState.NAVIGATING, FlightState.FAILSAFE_STOP, "no depth")
    normal = Transition(1.0, FlightState.TAKING_OFF, FlightState.ENTERING_OFFBOARD, "at height")
    warning = decoded(Log, topics.encode_transition(failsafe))
    assert warning.level == Log.WARNING and "failsafe_stop: no depth" in warning.message
    assert decoded(Log, topics.encode_transition(normal)).level == Log.INFO


def test_the_vins_health_carries_the_time_offset_in_use():
    """A field engineer reads the estimated camera-IMU offset off the recording (to put it
    into the vehicle's config as the next flight's ``vins.time_offset_s``)."""
    from autonomy.vins.estimator import FrameUpdate
    from autonomy.vins.health import Health, HealthState
    from autonomy.vins.time_offset import TimeOffset

    update = FrameUpdate(3.0, True, None, None, None, Health(HealthState.OK, "", 120, 60, 4.5),
                         TimeOffset(0.0148, 0.0006, estimating=True, updates=40))
    record = json.loads(topics.encode_vins_health(update))
    assert record["time_offset_s"] == 0.0148 and record["time_offset_sigma_s"] == 0.0006
    assert (record["state"], record["tracked"], record["landmarks"]) == ("ok", 120, 60)
    fixed = json.loads(topics.encode_vins_health(
        FrameUpdate(3.0, False, None, None, None, Health(HealthState.OK, ""))))
    assert fixed["time_offset_s"] == 0.0 and fixed["time_offset_sigma_s"] is None


def test_an_imu_sample_keeps_its_barometer_pressure_where_it_has_one():
    """A replay feeds the VINS the barometer the flight had (``companion replay``); a sample
    without one records no pressure at all, as the recordings made before it."""
    from autonomy.messages import ImuSample

    with_pressure = json.loads(topics.encode_imu(ImuSample(1.5, np.zeros(3), np.ones(3),
                                                           95590.25)))
    assert with_pressure["pressure_pa"] == 95590.25 and with_pressure["accel"] == [1.0] * 3
    assert "pressure_pa" not in json.loads(topics.encode_imu(ImuSample(1.5, np.zeros(3),
                                                                       np.ones(3))))
