"""A mock ROS 2 base for the ros2 tests and benchmark (named as such: it stands in for ``turtlebot3_node`` or a
Create 3): takes velocity on ``cmd_vel`` (TwistStamped, or Twist with ``--twist``), moves an ideal
differential base by it at 50 Hz, stops when commands stop for 0.5 s (as a Create 3 does), and
publishes ``nav_msgs/Odometry`` on ``odom`` at 30 Hz from ``--start X Y YAW``. Every command
received is printed as a JSON line ``{"v": .., "w": .., "t": monotonic}``, its own timeout
stopping it as ``{"timed_out": monotonic}``; a line ``pause`` on
stdin stops the odometry, ``resume`` starts it again, ``estop`` / ``estop-false`` publishes
``std_msgs/Bool`` true / false on ``estop`` (a ROS user's e-stop button). Run it only in a
loopback-only namespace."""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

from ovamos.shared.dds import check_loopback_only

check_loopback_only()

import rclpy  # noqa: E402  (after the check, by design)
from geometry_msgs.msg import Twist, TwistStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from nodes import serve  # noqa: E402  (this folder: the script's own)
from std_msgs.msg import Bool  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--twist", action="store_true", help="Twist on cmd_vel (a Create 3), else TwistStamped")
    parser.add_argument("--namespace", default="")
    parser.add_argument("--start", nargs=3, type=float, default=(0.0, 0.0, 0.0))
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node("fake_base", namespace=args.namespace or None)
    lock = threading.Lock()
    state = {"x": args.start[0], "y": args.start[1], "yaw": args.start[2], "v": 0.0, "w": 0.0,
             "last_cmd": -math.inf, "odom": True}

    def on_cmd(msg: Twist | TwistStamped) -> None:
        twist = msg if args.twist else msg.twist
        now = time.monotonic()
        with lock:
            state["v"], state["w"], state["last_cmd"] = twist.linear.x, twist.angular.z, now
        print(json.dumps({"v": twist.linear.x, "w": twist.angular.z, "t": now}), flush=True)

    node.create_subscription(Twist if args.twist else TwistStamped, "cmd_vel", on_cmd, 10)
    odom_pub = node.create_publisher(Odometry, "odom", 10)
    estop_pub = node.create_publisher(Bool, "estop", 10)

    def physics() -> None:
        with lock:
            if time.monotonic() - state["last_cmd"] > 0.5 and (state["v"] or state["w"]):
                state["v"] = state["w"] = 0.0  # the base's own command timeout, as a Create 3's
                print(json.dumps({"timed_out": time.monotonic()}), flush=True)
            dt = 0.02
            state["x"] += state["v"] * math.cos(state["yaw"]) * dt
            state["y"] += state["v"] * math.sin(state["yaw"]) * dt
            state["yaw"] += state["w"] * dt

    def publish() -> None:
        with lock:
            if not state["odom"]:
                return
            msg = Odometry()
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
            msg.pose.pose.position.x, msg.pose.pose.position.y = state["x"], state["y"]
            msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(state["yaw"] / 2), math.cos(state["yaw"] / 2)
            msg.twist.twist.linear.x, msg.twist.twist.angular.z = state["v"], state["w"]
        odom_pub.publish(msg)

    node.create_timer(0.02, physics)
    node.create_timer(1 / 30, publish)

    def read_stdin() -> None:
        for line in sys.stdin:
            said = line.strip()
            if said.startswith("estop"):
                estop_pub.publish(Bool(data=said == "estop"))
                continue
            with lock:
                state["odom"] = said != "pause"

    threading.Thread(target=read_stdin, daemon=True).start()
    serve(node)


if __name__ == "__main__":
    main()
