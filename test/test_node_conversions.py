"""Message <-> numpy helpers of bevo_node (no DDS: message classes only)."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")

from builtin_interfaces.msg import Time  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from bevo_ros.io import ros_conversions as rc  # noqa: E402


def _image(arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> Image:
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    row = arr.reshape(h, -1).view(np.uint8).reshape(h, -1)
    if pad:
        row = np.hstack([row, np.full((h, pad), 7, np.uint8)])
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian), step=row.shape[1])
    msg.data = row.tobytes()
    return msg


def test_stamps_round_trip_and_match_bag_formula():
    from bevo_ros.io import bag
    from bevo_ros.datasets import kitti

    t = Time(sec=1317388800, nanosec=123456789)
    assert rc.stamp_to_ns(t) == 1317388800123456789
    assert rc.stamp_to_sec(t) == 1317388800.0 + 123456789 * 1e-9  # sec + nanosec * 1e-9: rounded once
    assert rc.stamp_to_sec(t) == float(rc.ns_to_seconds([rc.stamp_to_ns(t)])[0])
    assert bag.ns_to_seconds is kitti.ns_to_seconds is rc.ns_to_seconds  # one formula for node, bags and KITTI
    from bevo_ros import pipeline, rotations

    # bag writer, bevo run and the node: one quaternion (bevo_ros.rotations, tested in test_rotations)
    assert bag.quaternion_from_rpy is rc.quaternion_from_rpy is pipeline.quaternion_from_rpy is rotations.quaternion_from_rpy
    back = rc.sec_to_stamp(1000.25)
    assert (back.sec, back.nanosec) == (1000, 250000000)
    edge = rc.sec_to_stamp(1.9999999999)
    assert (edge.sec, edge.nanosec) == (2, 0)


def test_mono8_with_row_padding_is_exact():
    img = np.arange(6 * 5, dtype=np.uint8).reshape(6, 5)
    out = rc.image_to_gray(_image(img, "mono8", pad=3))
    assert out.dtype == np.uint8 and np.array_equal(out, img)
    assert np.array_equal(rc.image_to_gray(_image(img, "8UC1")), img)


@pytest.mark.parametrize("enc", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_is_converted_with_bt601(enc):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (4, 7, 3), dtype=np.uint8)
    expected = np.clip(np.round(0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]), 0, 255)
    arr = rgb if enc.startswith("rgb") else rgb[..., ::-1]
    if enc.endswith("a8"):
        arr = np.concatenate([arr, np.full((4, 7, 1), 255, np.uint8)], -1)
    out = rc.image_to_gray(_image(arr, enc))
    assert np.abs(out.astype(int) - expected.astype(int)).max() <= 1


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_is_scaled_to_8_bits(bigendian):
    img = np.array([[0, 257, 65535], [1000, 30000, 65534]], dtype=">u2" if bigendian else "<u2")
    out = rc.image_to_gray(_image(img, "mono16", bigendian=bigendian))
    assert out.tolist() == [[0, 1, 255], [4, 117, 255]]


def test_unsupported_encoding_and_bad_sizes_name_the_reason():
    msg = _image(np.zeros((2, 2, 4), np.uint8), "32FC1")
    with pytest.raises(rc.ImageConversionError, match="unsupported image encoding '32FC1'") as err:
        rc.image_to_gray(msg)
    assert err.value.reason == "bad_encoding"
    short = _image(np.zeros((4, 4), np.uint8), "mono8")
    short.data = bytes(5)
    with pytest.raises(rc.ImageConversionError, match="data size") as err:
        rc.image_to_gray(short)
    assert err.value.reason == "bad_image"


def test_odometry_message_carries_step_and_stamp():
    from types import SimpleNamespace

    cov = np.arange(36, dtype=float).reshape(6, 6)
    step = SimpleNamespace(position=np.array([1.0, 2.0, 0.0]), rpy=np.array([0.01, -0.02, 0.3]),
                           pose_covariance=cov, twist_linear=np.array([5.0, 0.1, 0.0]),
                           twist_angular=np.array([0.0, 0.0, 0.2]), twist_covariance=cov.T)
    stamp = Time(sec=12, nanosec=34)
    msg = rc.odometry_msg(step, stamp, "odom", "base_link")
    assert msg.header.stamp == stamp and msg.header.frame_id == "odom" and msg.child_frame_id == "base_link"
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (1.0, 2.0)
    q = msg.pose.pose.orientation
    assert np.allclose(rc.rpy_from_quaternion(q.x, q.y, q.z, q.w), step.rpy, atol=1e-12)
    assert np.array_equal(np.asarray(msg.pose.covariance).reshape(6, 6), cov)
    assert np.array_equal(np.asarray(msg.twist.covariance).reshape(6, 6), cov.T)
    assert msg.twist.twist.linear.x == 5.0 and msg.twist.twist.angular.z == 0.2
    tf = rc.transform_from_odometry(msg)
    assert tf.header.frame_id == "odom" and tf.child_frame_id == "base_link"
    assert tf.transform.translation.y == 2.0 and tf.transform.rotation == msg.pose.pose.orientation


def test_camera_info_prefers_p_for_rectified_images():
    info = CameraInfo(width=640, height=480)
    info.k = [500.0, 0.0, 320.0, 0.0, 501.0, 240.0, 0.0, 0.0, 1.0]
    info.p = [400.0, 0.0, 300.0, 0.0, 0.0, 401.0, 200.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    K, w, h = rc.camera_info_intrinsics(info, use_p=True)
    assert (w, h) == (640, 480) and K[0, 0] == 400.0 and K[1, 2] == 200.0
    K, _, _ = rc.camera_info_intrinsics(info, use_p=False)
    assert K[0, 0] == 500.0
    with pytest.raises(ValueError, match="camera matrix"):
        rc.camera_info_intrinsics(CameraInfo(width=640, height=480))


def test_bev_and_heatmap_images():
    bev = np.linspace(0, 1, 16, dtype=np.float32).reshape(4, 4)
    mask = np.ones((4, 4), np.float32)
    mask[0] = 0
    img = rc.bev_to_mono8(bev, mask)
    assert img.dtype == np.uint8 and img[0].max() == 0 and img[-1, -1] == 255
    heat = rc.heatmap_to_mono8(np.array([[0.0, 1.0], [0.5, 0.0]]), (4, 6))
    assert heat.shape == (4, 6) and heat.max() == 255
    msg = rc.gray_to_image_msg(img)
    assert (msg.width, msg.height, msg.step, msg.encoding) == (4, 4, 4, "mono8")
    assert np.array_equal(rc.image_to_gray(msg), img)


# ------------------------------------------------------------------ camera encodings (issue 11)
def _colour_scene(h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth RGB image whose channels differ (a wrong Bayer/YUV layout shows)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 200 - 60 * np.sin(x / 9.0)
    g = 100 + 50 * np.cos(y / 7.0)
    b = 40 + 30 * np.sin((x + y) / 11.0)
    return np.clip(np.round(np.stack([r, g, b], -1)), 0, 255).astype(np.uint8)


def _bt601(rgb: np.ndarray) -> np.ndarray:
    f = rgb.astype(np.float64)
    return 0.299 * f[..., 0] + 0.587 * f[..., 1] + 0.114 * f[..., 2]


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_is_demosaiced_to_grey(pattern):
    rgb = _colour_scene()
    ch = {"r": 0, "g": 1, "b": 2}
    mosaic = np.zeros(rgb.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):  # pattern = 2x2 block, row-major
        mosaic[dy::2, dx::2] = rgb[dy::2, dx::2, ch[pattern[k]]]
    out = rc.image_to_gray(_image(mosaic, f"bayer_{pattern}8"))
    inner = (slice(4, -4), slice(4, -4))
    err = np.abs(out[inner].astype(np.float64) - _bt601(rgb)[inner])
    print(f"bayer_{pattern}8: mean |grey - BT.601| = {err.mean():.2f}")
    assert out.shape == mosaic.shape and out.dtype == np.uint8
    assert err.mean() < 4.0  # a wrong pattern (R and B swapped) is ~30 grey levels off here


@pytest.mark.parametrize("enc,layout", [("yuv422", "uyvy"), ("uyvy", "uyvy"), ("yuyv", "yuyv"),
                                        ("yuv422_yuy2", "yuyv")])
def test_packed_yuv422_gives_its_luma(enc, layout):
    rng = np.random.default_rng(1)
    luma = rng.integers(16, 236, size=(6, 8), dtype=np.uint8)
    chroma = rng.integers(16, 240, size=(6, 8), dtype=np.uint8)
    packed = np.stack([chroma, luma], -1) if layout == "uyvy" else np.stack([luma, chroma], -1)
    msg = _image(packed, enc, pad=4)  # 2 bytes per pixel, padded rows
    msg.width = 8
    assert rc.image_to_gray(msg).tolist() == luma.tolist()


def test_compressed_png_and_jpeg_are_decoded():
    import cv2
    from sensor_msgs.msg import CompressedImage

    grey = np.round(_bt601(_colour_scene())).astype(np.uint8)
    png = CompressedImage(format="mono8; png compressed ")
    png.data = cv2.imencode(".png", grey)[1].tobytes()
    assert np.array_equal(rc.image_to_gray(png), grey)
    jpg = CompressedImage(format="rgb8; jpeg compressed bgr8")
    jpg.data = cv2.imencode(".jpg", cv2.cvtColor(_colour_scene(), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    assert np.abs(rc.image_to_gray(jpg).astype(float) - _bt601(_colour_scene())).mean() < 3.0
    broken = CompressedImage(format="jpeg")
    broken.data = b"not an image"
    with pytest.raises(rc.ImageConversionError, match="cannot be decoded") as err:
        rc.image_to_gray(broken)
    assert err.value.reason == "bad_compressed"


# ------------------------------------------------------------------ distortion (issue 11)
def _camera_info(w, h, K, D=(), model="plumb_bob", P=None):
    info = CameraInfo(width=w, height=h, distortion_model=model)
    info.k = np.asarray(K, float).reshape(-1).tolist()
    info.d = list(map(float, D))
    info.r = np.eye(3).reshape(-1).tolist()
    P = np.hstack([np.asarray(K, float), np.zeros((3, 1))]) if P is None else np.asarray(P, float)
    info.p = P.reshape(-1).tolist()
    return info


def test_distorted_camera_info_builds_undistortion_maps_that_invert_the_lens():
    import cv2

    from bevo_ros.ros.camera import CalibrationError, calibration_from_camera_info

    w, h = 320, 240
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    D = np.array([-0.3, 0.1, 0.001, -0.002, 0.0])
    # a textured undistorted scene, and what the lens makes of it: for each distorted pixel, the
    # undistorted pixel it sees
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), 2.0)
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    und = cv2.undistortPoints(grid, K, D, P=K).reshape(h, w, 2).astype(np.float32)
    distorted = cv2.remap(scene, und[..., 0], und[..., 1], cv2.INTER_LINEAR)

    calib = calibration_from_camera_info(_camera_info(w, h, K, D), image_topic="camera/image_raw")
    assert calib.maps is not None and "undistorted" in calib.source
    restored = calib.rectify(distorted)
    inner = (slice(40, -40), slice(50, -50))
    err_restored = np.abs(restored[inner].astype(float) - scene[inner]).mean()
    err_raw = np.abs(distorted[inner].astype(float) - scene[inner]).mean()
    print(f"undistortion: mean abs error {err_restored:.2f} grey levels (distorted image: {err_raw:.2f})")
    assert err_restored < 2.0 < err_raw
    np.testing.assert_allclose(calib.K, K)

    # image_rect* are rectified by image_proc with this very CameraInfo: P describes them as they are
    assert calibration_from_camera_info(_camera_info(w, h, K, D), image_topic="camera/image_rect").maps is None
    assert calibration_from_camera_info(_camera_info(w, h, K, D), undistort="on",
                                        image_topic="camera/image_rect").maps is not None
    assert calibration_from_camera_info(_camera_info(w, h, K, D), undistort="off",
                                        image_topic="camera/image_raw").maps is None
    assert calibration_from_camera_info(_camera_info(w, h, K), image_topic="camera/image_raw").maps is None
    fisheye = calibration_from_camera_info(_camera_info(w, h, K, [0.1, 0.01, 0.0, 0.0], "equidistant"),
                                           image_topic="camera/image_raw")
    assert fisheye.maps is not None
    with pytest.raises(CalibrationError, match="distortion_model 'kannala_unknown'.*not supported"):
        calibration_from_camera_info(_camera_info(w, h, K, D, "kannala_unknown"), image_topic="camera/image_raw")


def test_rgb8_bag_gives_the_node_s_grey_levels_for_every_colour(tmp_path):
    """One conversion: an rgb8 image read back from a rosbag2 by the offline tools (bag.decode_image,
    run_bag, training) has exactly the grey levels the node computes from the same message, for all
    2^24 colours (a float64 copy of the BT.601 formula rounds 2,743 of them differently)."""
    from bevo_ros.io import bag

    rgb = np.arange(1 << 24, dtype=np.uint32).view(np.uint8).reshape(4096, 4096, 4)[..., :3].copy()
    path = tmp_path / "rgb_bag"
    with bag.BagWriter(path, storage="mcap") as writer:
        writer.write(bag.IMAGE_TOPIC, bag.IMAGE_MSG, bag.image_message(1.0, rgb, "camera", "rgb8"), 1.0)
    (_, _, stored), = list(bag.iter_messages(path, [bag.IMAGE_TOPIC]))
    offline = bag.decode_image(stored)
    node = rc.image_to_gray(_image(rgb, "rgb8"))
    assert offline.shape == node.shape == (4096, 4096)
    assert np.array_equal(offline, node)
    f64 = np.clip(np.round(0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]), 0, 255)
    differ = int((f64 != node).sum())
    print(f"\nfloat64 BT.601 differs from the one conversion on {differ} of {1 << 24} colours (by at most 1)")
    assert 0 < differ and np.abs(f64 - node).max() == 1  # the comparison above can see such a drift


def test_offline_decoder_takes_the_same_camera_encodings():
    """bag.decode_image (run_bag, training) decodes Bayer, YUV and compressed images as the node does."""
    import cv2

    from bevo_ros.io import bag

    types = bag.typestore().types
    grey = np.round(_bt601(_colour_scene())).astype(np.uint8)
    hdr = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="c")
    packed = np.stack([np.full_like(grey, 128), grey], -1)  # UYVY: chroma, luma
    yuv = types["sensor_msgs/msg/Image"](header=hdr, height=grey.shape[0], width=grey.shape[1], encoding="uyvy",
                                         is_bigendian=0, step=grey.shape[1] * 2, data=packed.reshape(-1).copy())
    assert np.array_equal(bag.decode_image(yuv), grey)
    png = types["sensor_msgs/msg/CompressedImage"](header=hdr, format="png",
                                                   data=cv2.imencode(".png", grey)[1].reshape(-1))
    assert np.array_equal(bag.decode_image(png), grey)
    ros_msg = _image(packed, "uyvy")
    ros_msg.width = grey.shape[1]
    assert np.array_equal(rc.image_to_gray(ros_msg), bag.decode_image(yuv))


def test_static_lookups_strip_a_leading_slash_for_tf2_and_the_tree():
    """ROS 1 bags name frames '/base_link': tf2's buffer strips the slash from the transforms but
    refuses it in a lookup, so the node strips it before asking (as its own tree does)."""
    from types import SimpleNamespace

    from bevo_ros.io.static_tf import StaticTree
    from bevo_ros.ros.tf import StaticTransforms

    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    tree = StaticTree()
    tree.add("/base_link", "/camera", T)
    assert np.allclose(tree.lookup("/base_link", "camera"), T) and np.allclose(tree.lookup("base_link", "/camera"), T)

    class Tf2Buffer:  # tf2's rule: no leading '/' in a lookup
        def lookup_transform(self, target, source, _time):
            if target.startswith("/") or source.startswith("/"):
                raise ValueError("in tf2 frame_ids cannot start with a '/'")
            tr = SimpleNamespace(translation=SimpleNamespace(x=1.0, y=2.0, z=3.0),
                                 rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0))
            return SimpleNamespace(transform=tr)

    static = StaticTransforms.__new__(StaticTransforms)  # the tf2_ros backend without a node
    static._buffer, static.tree = Tf2Buffer(), StaticTree()
    assert np.allclose(static.lookup("/base_link", "/camera"), T)
    assert static.lookup("/", "/camera") is None
