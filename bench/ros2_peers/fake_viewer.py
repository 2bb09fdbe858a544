"""A mock ROS 2 viewer for the rosview tests (named as such: it stands in for RViz): subscribes to
``/ovamos/map``, ``/ovamos/value/<target>`` for each ``--layer``, ``/ovamos/path`` and
``/ovamos/markers`` with the QoS deploy/ros2/ovamos.rviz gives RViz for them (transient-local: a viewer
that joins late gets what is shown), and prints a JSON line per message received
(what it would draw). Run it only in a loopback-only namespace."""

from __future__ import annotations

import argparse
import json

from ovamos.shared.dds import check_loopback_only

check_loopback_only()

import rclpy  # noqa: E402  (after the check, by design)
from nav_msgs.msg import OccupancyGrid, Path  # noqa: E402
from nodes import serve  # noqa: E402  (this folder: the script's own)
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--layer", action="append", default=[])
    args = parser.parse_args()
    rclpy.init()
    node = rclpy.create_node("fake_viewer")
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

    def on_grid(topic: str):
        def got(msg: OccupancyGrid) -> None:
            data = list(msg.data)
            print(json.dumps({"topic": topic, "frame": msg.header.frame_id, "width": msg.info.width,
                              "height": msg.info.height, "resolution": msg.info.resolution,
                              "origin": [msg.info.origin.position.x, msg.info.origin.position.y],
                              "unknown": data.count(-1), "free": data.count(0), "occupied": data.count(100),
                              "max": max(data, default=-1), "first_row_occupied": data[: msg.info.width].count(100)}),
                  flush=True)
        return got

    for topic in ["/ovamos/map", *(f"/ovamos/value/{layer}" for layer in args.layer)]:
        node.create_subscription(OccupancyGrid, topic, on_grid(topic), latched)
    node.create_subscription(Path, "/ovamos/path", lambda m: print(json.dumps(
        {"topic": "/ovamos/path", "poses": [[p.pose.position.x, p.pose.position.y] for p in m.poses]}), flush=True),
        latched)
    node.create_subscription(MarkerArray, "/ovamos/markers", lambda m: print(json.dumps(
        {"topic": "/ovamos/markers", "marks": [[k.ns, k.pose.position.x, k.pose.position.y, k.text]
                                              for k in m.markers if k.action == 0]}), flush=True), latched)
    serve(node)


if __name__ == "__main__":
    main()
