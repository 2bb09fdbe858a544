"""The Foxglove layout of the view channels, built with the SDK's layout model (so it stays a
valid layout) and shipped as ``deploy/foxglove/ovamos.json``.

Camera colour over depth on the left; the map (obstacles, explored area, frontiers, objects, the
robot's path, the planner's candidates and goal) seen from above, following the robot, with the
value layers (``/map/value/<target>``, named by the task) to switch on in the panel's topics;
task events and decisions as a log under it. Regenerate the file
with ``python -m ovamos.record.layout deploy/foxglove/ovamos.json`` (a test checks it is current).
"""

from __future__ import annotations

import sys
from pathlib import Path

import foxglove.layouts as fl

from ovamos.record.views import BASE
from ovamos.shared.deploy import DEPLOY_DIR

__all__ = ["layout", "LAYOUT_FILE"]

LAYOUT_FILE = DEPLOY_DIR / "foxglove" / "ovamos.json"


def _grid(low: str, high: str, max_value: float = 1.0) -> fl.BaseRendererGridTopicSettings:
    return fl.BaseRendererGridTopicSettings(visible=True, color_mode="gradient", gradient=(low, high),
                                            min_value=0.0, max_value=max_value)


def layout() -> fl.Layout:
    grids = {"/map/explored": _grid("#46464600", "#ebebebff"), "/map/obstacle": _grid("#00000000", "#000000ff")}
    shapes = {t: fl.BaseRendererSceneUpdateTopicSettings(visible=True)
              for t in ("/map/frontiers", "/map/objects", "/planner/candidates", "/planner/goal")}
    poses = {"/robot/pose": fl.BaseRendererPoseTopicSettings(visible=True),
             "/robot/path": fl.BaseRendererPosesTopicSettings(visible=True)}
    map_panel = fl.ThreeDeePanel(title="map, path and planner", config=fl.ThreeDeeConfig(
        follow_tf=BASE, follow_mode="follow-position",
        camera_state=fl.ThreeDeeCameraState(perspective=False, distance=15.0),
        topics={**grids, **shapes, **poses}))
    camera = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=fl.ImagePanel(title="colour", config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(image_topic="/camera/color")))),
        fl.SplitItem(content=fl.ImagePanel(title="depth", config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(image_topic="/camera/depth", color_mode="colormap", color_map="turbo")))),
    ])
    right = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=3, content=map_panel),
        fl.SplitItem(proportion=1, content=fl.LogPanel(title="task and decisions",
                                                       config=fl.LogConfig(topic_to_render="/log"))),
    ])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=camera), fl.SplitItem(proportion=3, content=right)]))


if __name__ == "__main__":
    Path(sys.argv[1] if len(sys.argv) > 1 else LAYOUT_FILE).write_text(layout().to_json() + "\n")
