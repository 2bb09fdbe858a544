"""What rosview draws, computed without ROS (services/rosview/convert.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ovamos.services.rosview.convert import Mark, marks, occupancy, value_cells
from ovamos.shared.messages import DecisionTrace, Goal, MapSnapshot, ObjectInstance, TraceOption


def snapshot() -> MapSnapshot:
    obstacle, explored = np.zeros((4, 5), bool), np.zeros((4, 5), bool)
    explored[:2] = True
    obstacle[0, 1] = True
    values = np.zeros((2, 4, 5), np.float32)
    values[0, 1, 3], values[1, 0, 0] = 0.5, 0.2
    return MapSnapshot(seq=1, after_action=1, stamp=0.0, resolution=0.05, origin=(0.0, 0.0), layers=("cup", "bed"),
                       objects=(ObjectInstance(label="bed", x=1.0, y=2.0, score=0.4, hits=1),),
                       obstacle=obstacle, explored=explored, counts=np.ones((2, 4, 5), np.uint16), values=values,
                       frontiers=np.array([[0.1, 0.2]]))


def test_cells_are_unknown_free_or_occupied_and_values_0_to_100() -> None:
    snap = snapshot()
    cells = occupancy(snap)
    assert cells.dtype == np.int8 and cells[0, 1] == 100 and cells[0, 0] == 0 and (cells[2:] == -1).all()
    cup = value_cells(snap, "cup")
    assert cup[1, 3] == 100 and (cup[2:] == -1).all() and cup[0, 0] == 0  # normalised to its peak


def test_marks_are_the_frontiers_objects_candidates_and_goal() -> None:
    trace = DecisionTrace(task_id="t", step=1, stamp=0.0, map_seq=1, robot_x=0.0, robot_y=0.0, remaining=("bed",),
                          options=(TraceOption(kind="candidate", x=3.0, y=1.0, value=0.2),
                                   TraceOption(kind="frontier", x=0.1, y=0.2, value=0.0)),
                          goal=Goal(kind="frontier", x=0.1, y=0.2), reason="explore")
    assert marks(snapshot(), trace) == [Mark("frontier", 0.1, 0.2), Mark("object", 1.0, 2.0, "bed"),
                                        Mark("candidate", 3.0, 1.0), Mark("goal", 0.1, 0.2, "frontier")]
    assert marks(None, None) == []


def test_the_shipped_rviz_config_shows_what_rosview_publishes() -> None:
    import yaml

    from ovamos.services.rosview.config import RosViewConfig
    layout = yaml.safe_load((Path(__file__).resolve().parent.parent / "deploy" / "ros2" / "ovamos.rviz").read_text())
    manager = layout["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == RosViewConfig().frame_id
    shown = {d["Topic"]["Value"] for d in manager["Displays"] if "Topic" in d}
    prefix = RosViewConfig().prefix
    assert shown == {f"{prefix}/map", f"{prefix}/path", f"{prefix}/markers"}
