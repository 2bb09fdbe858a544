"""Where the search for each target got to: in view, detected, confirmed on the map, STOPped at.

A failed episode says only that some target was not found. The stage a target never reached
says why, and points at the part to improve: never in view (exploration), in view but never
detected (the detector, or views too far or too occluded), detected but never confirmed (the
object map's evidence rule), confirmed but not reached in time (navigation, the step limit), or
a wrong STOP (a false object confirmed and stopped at: the target is then lost).

The runner holds the ground truth, so it can tell a true detection from a false one; the
policies never see this record.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from pydantic import BaseModel

from ovamos.shared.detections import Detection
from ovamos.shared.messages import Miss, ObjectInstance, RgbdFrame
from ovamos.world.occupancy import distance_to_box
from ovamos.world.scene import Scene

#: A confirmed map object this close (horizontal, m) to a true instance's footprint is that
#: instance: about the object map's merge distance, well under the gap between two pieces of
#: furniture that a false detection would stand for.
TRUE_OBJECT_M = 0.5


class StopRecord(BaseModel):
    """One STOP of an episode, scored by the ground truth: the funnel's last stage."""

    step: int
    label: str
    x: float
    y: float
    success: bool
    distance_m: float  # geodesic distance to the nearest true instance


class TargetFunnel(BaseModel):
    """The first step at which one target reached each stage (None: never)."""

    label: str
    seen: int | None = None        # a true instance in view (as many pixels as perception needs)
    detected: int | None = None    # a true instance detected
    confirmed: int | None = None   # a confirmed map object near a true instance
    stopped: int | None = None     # a correct STOP (the target found)
    wrong_stops: int = 0

    @property
    def miss(self) -> Miss | None:
        if self.stopped is not None:
            return None
        if self.wrong_stops:
            return Miss.WRONG_STOP
        for stage, miss in ((self.seen, Miss.NEVER_SEEN), (self.detected, Miss.NOT_DETECTED),
                            (self.confirmed, Miss.NOT_CONFIRMED)):
            if stage is None:
                return miss
        return Miss.NOT_REACHED


class FunnelRecorder:
    """Fed by the episode runner once per step with what the services produced; the STOPs come
    from the runner's own record at the end."""

    def __init__(self, scene: Scene, targets: Sequence[str]) -> None:
        self.scene = scene
        self.funnels = {t: TargetFunnel(label=t) for t in targets}

    def frame(self, step: int, frame: RgbdFrame, visible: set[str], detections: Sequence[Detection]) -> None:
        """``visible``: the classes perception could see in the frame; ``detections``: its output
        (a simulated detection's mask covers exactly one instance, whose id tells its class)."""
        for label, funnel in self.funnels.items():
            if funnel.seen is None and label in visible:
                funnel.seen = step
        if frame.instance_ids is None:
            return
        for det in detections:
            funnel = self.funnels.get(det.label)
            if funnel is None or funnel.detected is not None or not det.mask.any():
                continue
            instance = int(frame.instance_ids[det.mask][0])
            if instance > 0 and self.scene.object(instance).cls == det.label:
                funnel.detected = step

    def map(self, step: int, objects: Sequence[ObjectInstance]) -> None:
        """``objects``: the map snapshot's object instances."""
        for obj in objects:
            funnel = self.funnels.get(obj.label)
            if funnel is not None and funnel.confirmed is None and obj.confirmed and self._true(obj):
                funnel.confirmed = step

    def _true(self, obj: ObjectInstance) -> bool:
        x, y = np.array([obj.x]), np.array([obj.y])
        return any(float(distance_to_box(o, x, y)[0]) <= TRUE_OBJECT_M for o in self.scene.instances(obj.label))

    def result(self, stops: Iterable[StopRecord]) -> list[TargetFunnel]:
        """The funnels, with the episode's STOPs (the runner's record of them) as the last stage."""
        for stop in stops:
            funnel = self.funnels[stop.label]
            if stop.success:
                funnel.stopped = stop.step
            else:
                funnel.wrong_stops += 1
        return list(self.funnels.values())
