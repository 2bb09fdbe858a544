"""The ``rosview`` service: the search on ROS 2 topics, for RViz (``deploy/ros2/ovamos.rviz``) and
``ros2 bag``.

From the robot's map snapshots, odometry and the planner's decisions it publishes, in the
map's frame (``frame_id``: the odometry frame, unless the map localizes; the path's odometry is
placed in it by the snapshot's ``map_T_odom``) under ``prefix``:

* ``<prefix>/map``: ``nav_msgs/OccupancyGrid`` of the obstacles (:func:`convert.occupancy`);
  ``<prefix>/value/<target>``: one per value layer, the map the planner decides on for it.
  Reliable and transient-local, so an RViz started later gets the latest at once.
* ``<prefix>/path``: ``nav_msgs/Path`` of the robot's poses (one every ``path_step_m``, at most
  ``path_poses``), transient-local too: it changes only while the robot moves.
* ``<prefix>/markers``: ``visualization_msgs/MarkerArray``: frontiers, candidates of the latest
  decision, its goal, and the map's objects (confirmed ones larger), labelled; transient-local,
  each array the whole picture (it starts with a DELETEALL), so a viewer that joins late draws it.

What the API drops goes from ROS too: when the task ends (a final ``task/events``) the decision's
candidates and goal go, and a value layer the map no longer has is published empty.

It only reads our topics and publishes ROS ones: it runs wherever rclpy and the robot's ROS graph
are (the laptop or the robot), and nothing of the search waits for it.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from ovamos.services.rosview.config import RosViewConfig
from ovamos.services.rosview.convert import Mark, marks, occupancy, value_cells
from ovamos.shared.bus import BusCore
from ovamos.shared.messages import FINAL, DecisionTrace, MapSnapshot, Odometry, TaskEvent
from ovamos.shared.motion import Pose
from ovamos.shared.ros2 import Ros2Unavailable, node
from ovamos.shared.service import Service
from ovamos.shared.sessions import SessionFollower

COLOURS: dict[str, tuple[float, float, float]] = {
    "frontier": (0.2, 0.6, 1.0), "candidate": (1.0, 0.6, 0.0), "goal": (1.0, 0.0, 1.0),
    "object": (0.9, 0.9, 0.2), "confirmed": (0.1, 0.9, 0.2)}
"""Marker colours (RGB 0-1): close to the operator page's."""


class RosViewService(Service):
    name = "rosview"
    Config = RosViewConfig
    config: RosViewConfig

    def __init__(self, bus: BusCore, config: RosViewConfig) -> None:
        super().__init__(bus, config)
        self.tick_hz = config.publish_hz
        self._snapshot: MapSnapshot | None = None
        self._trace: DecisionTrace | None = None
        self._path: deque[Odometry] = deque(maxlen=config.path_poses)
        self.sessions = SessionFollower(config.session_switch)
        self._changed = {"map": False, "path": False, "markers": False}
        self._pubs: dict[str, Any] = {}
        self._layers: set[str] = set()  # the value layers published last
        self.published: dict[str, int] = {}

    def start(self) -> None:
        try:
            self._ros = node(self.config.network)
        except Ros2Unavailable as exc:
            raise RuntimeError(f"rosview cannot start ROS 2: {exc}") from None
        self.wire({"map_snapshot": self._on_snapshot, "odom": self._on_odom, "plan_trace": self._on_trace,
                   "task_events": self._on_event})

    def _on_snapshot(self, snapshot: MapSnapshot) -> None:
        moved = self._snapshot is None or self._snapshot.map_T_odom != snapshot.map_T_odom
        self._snapshot = snapshot
        self._changed["map"] = self._changed["markers"] = True
        self._changed["path"] = self._changed["path"] or (moved and bool(self._path))

    def _on_trace(self, trace: DecisionTrace) -> None:
        self._trace = trace
        self._changed["markers"] = True

    def _on_event(self, event: TaskEvent) -> None:
        """A task that ended takes its decision's candidates and goal with it."""
        if event.status in FINAL and self._trace is not None and self._trace.task_id == event.task_id:
            self._trace = None
            self._changed["markers"] = True

    def _on_odom(self, odom: Odometry) -> None:
        """The robot's path, of the driver's odometry session only (followed on evidence, as every
        consumer of odometry: a forged stream is counted, not drawn)."""
        before = self.sessions.current
        if not self.sessions.observe("odom", odom.odom_session, odom.seq):
            return
        last = self._path[-1] if self._path else None
        if before is not None and odom.odom_session != before:
            self._path.clear()  # a restarted driver: a path of the new odometry frame
        elif last is not None and math.hypot(odom.x - last.x, odom.y - last.y) < self.config.path_step_m:
            return
        self._path.append(odom)
        self._changed["path"] = True

    def tick(self) -> None:
        if self._changed["map"] and self._snapshot is not None:
            self._publish_grid("map", occupancy(self._snapshot))
            for layer in self._snapshot.layers:
                self._publish_grid(f"value/{layer}", value_cells(self._snapshot, layer))
            for gone in self._layers - set(self._snapshot.layers):  # a target no longer searched
                self._publish_grid(f"value/{gone}", np.zeros((0, 0), np.int8))
            self._layers = set(self._snapshot.layers)
        if self._changed["path"]:
            self._publish_path()
        if self._changed["markers"]:
            self._publish_markers(marks(self._snapshot, self._trace))
        self._changed = dict.fromkeys(self._changed, False)

    def _publisher(self, name: str, kind: type, latched: bool = False) -> Any:
        pub = self._pubs.get(name)
        if pub is None:
            from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
            qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            pub = self._pubs[name] = self._ros.create_publisher(kind, f"{self.config.prefix}/{name}", qos)
        return pub

    def _header(self, msg: Any) -> Any:
        msg.header.stamp = self._ros.get_clock().now().to_msg()
        msg.header.frame_id = self.config.frame_id
        return msg

    def _count(self, name: str) -> None:
        self.published[name] = self.published.get(name, 0) + 1

    def _publish_grid(self, name: str, cells: np.ndarray) -> None:
        from nav_msgs.msg import OccupancyGrid
        snap = self._snapshot
        assert snap is not None
        grid = self._header(OccupancyGrid())
        grid.info.resolution = float(snap.resolution)
        grid.info.height, grid.info.width = (int(n) for n in cells.shape)
        grid.info.origin.position.x, grid.info.origin.position.y = float(snap.origin[0]), float(snap.origin[1])
        grid.info.origin.orientation.w = 1.0
        grid.data = cells.ravel().tolist()
        self._publisher(name, OccupancyGrid, latched=True).publish(grid)
        self._count(name)

    def _publish_path(self) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path
        path = self._header(Path())
        snap = self._snapshot
        for odom in self._path:
            at = Pose(x=odom.x, y=odom.y, yaw=odom.yaw)
            if snap is not None and snap.odom_session == odom.odom_session:
                at = snap.to_map(at)  # where the map has it (localization's map_T_odom)
            pose = PoseStamped()
            pose.header.frame_id = self.config.frame_id
            pose.pose.position.x, pose.pose.position.y = at.x, at.y
            pose.pose.orientation.z, pose.pose.orientation.w = math.sin(at.yaw / 2), math.cos(at.yaw / 2)
            path.poses.append(pose)
        self._publisher("path", Path, latched=True).publish(path)
        self._count("path")

    def _publish_markers(self, shown: list[Mark]) -> None:
        from visualization_msgs.msg import Marker, MarkerArray
        array = MarkerArray()
        clear = self._header(Marker())
        clear.action = Marker.DELETEALL  # the marks of before go: each array is the whole picture
        array.markers.append(clear)
        for i, mark in enumerate(shown):
            sphere = self._header(Marker())
            sphere.ns, sphere.id, sphere.type, sphere.action = mark.kind, i, Marker.SPHERE, Marker.ADD
            size = {"frontier": 0.1, "candidate": 0.15, "goal": 0.3, "object": 0.2, "confirmed": 0.35}[mark.kind]
            sphere.scale.x = sphere.scale.y = sphere.scale.z = size
            sphere.pose.position.x, sphere.pose.position.y = mark.x, mark.y
            sphere.pose.orientation.w = 1.0
            sphere.color.r, sphere.color.g, sphere.color.b = COLOURS[mark.kind]
            sphere.color.a = 0.9
            array.markers.append(sphere)
            if mark.label:
                text = self._header(Marker())
                text.ns, text.id, text.type, text.action = f"{mark.kind}/label", i, Marker.TEXT_VIEW_FACING, Marker.ADD
                text.text, text.scale.z = mark.label, 0.2
                text.pose.position.x, text.pose.position.y, text.pose.position.z = mark.x, mark.y, size + 0.15
                text.pose.orientation.w = 1.0
                text.color.r = text.color.g = text.color.b = text.color.a = 1.0
                array.markers.append(text)
        self._publisher("markers", MarkerArray, latched=True).publish(array)
        self._count("markers")

    def info(self) -> dict[str, Any]:
        return {"published": dict(self.published), "path_poses": len(self._path),
                "map_seq": None if self._snapshot is None else self._snapshot.seq, "sessions": self.sessions.info()}
