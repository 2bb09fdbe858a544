"""A mock ROS 2 RGB-D camera for the ros2 tests and benchmark (named as such: it stands in for realsense2_camera):
colour, depth aligned to it and the colour camera's info, one stamp each, at ``--hz`` (15) on
``/camera/camera/...``, ``--width`` x ``--height`` (64 x 48). The colour's red channel is the column, green the row; depth is 1.234 m
with the top-left 4 x 4 pixels 0 (no reading) and, in 32FC1, the next 4 NaN. With
``--ids-encoding`` it also publishes a simulated camera's instance ids (the column) on
``/camera/camera/instance_ids``. Options make each fault a camera can have. Run it only in a loopback-only namespace."""

from __future__ import annotations

import argparse

import numpy as np

from ovamos.shared.dds import check_loopback_only

check_loopback_only()

import rclpy  # noqa: E402  (after the check, by design)
from nodes import serve  # noqa: E402  (this folder: the script's own)
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

FX, FY = 50.0, 52.0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--depth-encoding", default="16UC1", choices=["16UC1", "32FC1"])
    parser.add_argument("--color-encoding", default="rgb8", help="rgb8, bgr8, or another to be refused")
    parser.add_argument("--no-info", action="store_true")
    parser.add_argument("--depth-width", type=int, default=0, help="0: the colour's width")
    parser.add_argument("--depth-offset-s", type=float, default=0.0, help="depth stamped this much later")
    parser.add_argument("--ids-encoding", default="", help="publish instance ids in it (32SC1; another "
                        "to be refused); none: no ids")
    parser.add_argument("--ids-width", type=int, default=0, help="0: the colour's width")
    parser.add_argument("--best-effort", action="store_true", help="publish best effort (else reliable)")
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--height", type=int, default=48)
    parser.add_argument("--hz", type=float, default=15.0)
    args = parser.parse_args()
    W, H = args.width, args.height
    K = (FX, 0.0, (W - 1) / 2, 0.0, FY, (H - 1) / 2, 0.0, 0.0, 1.0)
    rclpy.init()
    node = rclpy.create_node("fake_camera")
    qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT if args.best_effort
                     else ReliabilityPolicy.RELIABLE)
    color_pub = node.create_publisher(Image, "/camera/camera/color/image_raw", qos)
    depth_pub = node.create_publisher(Image, "/camera/camera/aligned_depth_to_color/image_raw", qos)
    info_pub = node.create_publisher(CameraInfo, "/camera/camera/color/camera_info", qos)
    ids_pub = node.create_publisher(Image, "/camera/camera/instance_ids", qos)
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    rgb = np.stack([cols, rows, np.full_like(cols, 7)], axis=-1).astype(np.uint8)
    dw = args.depth_width or W
    metres = np.full((H, dw), 1.234, np.float32)
    metres[:4, :4] = 0.0
    if args.depth_encoding == "32FC1":
        metres[:4, 4:8] = np.nan
        depth_bytes, depth_step = metres.tobytes(), dw * 4
    else:
        depth_bytes, depth_step = np.rint(metres * 1000).astype("<u2").tobytes(), dw * 2
    iw = args.ids_width or W
    ids = np.ascontiguousarray(np.broadcast_to(np.arange(iw, dtype="<i4"), (H, iw)))

    def publish() -> None:
        now = node.get_clock().now()
        stamp = now.to_msg()
        color = Image(height=H, width=W, encoding=args.color_encoding, step=W * 3,
                      data=(rgb[:, :, ::-1] if args.color_encoding == "bgr8" else rgb).tobytes())
        color.header.stamp, color.header.frame_id = stamp, "camera_color_optical_frame"
        depth = Image(height=H, width=dw, encoding=args.depth_encoding, step=depth_step, data=depth_bytes)
        depth.header.stamp = (now + rclpy.duration.Duration(seconds=args.depth_offset_s)).to_msg()
        info = CameraInfo(height=H, width=W, k=list(K))
        info.header.stamp = stamp
        color_pub.publish(color)
        depth_pub.publish(depth)
        if not args.no_info:
            info_pub.publish(info)
        if args.ids_encoding:
            ids_msg = Image(height=H, width=iw, encoding=args.ids_encoding, step=iw * 4, data=ids.tobytes())
            ids_msg.header.stamp = stamp
            ids_pub.publish(ids_msg)

    node.create_timer(1 / args.hz, publish)
    serve(node)


if __name__ == "__main__":
    main()
