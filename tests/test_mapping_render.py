"""Map pictures: a hand-built snapshot whose every cell is known, read back pixel by pixel."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from ovamos.services.mapping import render
from ovamos.services.mapping.render import render_map, value_image, write_png
from ovamos.shared.messages import MapSnapshot, ObjectInstance

ROWS, COLS, RES = 200, 300, 0.05
X0, Y0 = -1.0, -2.0
PPC = 2
EXPLORED = np.s_[50:81, 100:151]   # rows 50..80, cols 100..150
WALL_ROW = 80                      # obstacle along the explored patch's top edge
POST = (60, 110)                   # a single obstacle cell
HOT, WARM = (70, 130), (70, 140)   # value cells
FRONTIER_CELL = (65, 100)
CUP_CELL, BED_CELL = (55, 140), (75, 105)
ROBOT_CELL = (58, 125)
MARGIN = 10
CROP = (50 - MARGIN, 81 + MARGIN, 100 - MARGIN, 151 + MARGIN)  # r0, r1, c0, c1


def centre(cell: tuple[int, int]) -> tuple[float, float]:
    """World (x, y) of a cell's centre."""
    r, c = cell
    return X0 + (c + 0.5) * RES, Y0 + (r + 0.5) * RES


def snapshot(**changes) -> MapSnapshot:
    explored = np.zeros((ROWS, COLS), bool)
    explored[EXPLORED] = True
    obstacle = np.zeros((ROWS, COLS), bool)
    obstacle[WALL_ROW, 100:151] = True
    obstacle[POST] = True
    values = np.zeros((2, ROWS, COLS), np.float32)
    values[0][HOT], values[0][WARM] = 1.0, 0.2  # "cup": HOT is the peak, WARM a fifth of it
    values[1][WARM] = 4.0                        # "bed": only WARM
    fields = dict(
        seq=3, stamp=1.0, resolution=RES, origin=(X0, Y0), layers=("cup", "bed"),
        objects=(ObjectInstance(label="cup", x=centre(CUP_CELL)[0], y=centre(CUP_CELL)[1],
                                score=0.8, hits=3, confirmed=True),
                 ObjectInstance(label="bed", x=centre(BED_CELL)[0], y=centre(BED_CELL)[1],
                                score=0.5, hits=1, confirmed=False)),
        obstacle=obstacle, explored=explored, counts=np.zeros((2, ROWS, COLS), np.uint16),
        values=values, frontiers=np.array([centre(FRONTIER_CELL)]))
    fields.update(changes)
    return MapSnapshot(**fields)


def pixel(image: np.ndarray, cell: tuple[int, int], crop: tuple[int, int, int, int] | None = None
          ) -> np.ndarray:
    """The BGR pixel at the centre of ``cell``'s square in a picture (flipped: up = +y)."""
    r0, r1, c0, c1 = crop or (0, ROWS, 0, COLS)
    r, c = cell
    return image[(r1 - 1 - r) * PPC + PPC // 2, (c - c0) * PPC + PPC // 2]


def around(image: np.ndarray, cell: tuple[int, int], reach: int = 7) -> np.ndarray:
    """The pixels within ``reach`` of ``cell``'s square in an uncropped picture."""
    r, c = cell
    return image[(ROWS - 1 - r) * PPC - reach:(ROWS - r) * PPC + reach, c * PPC - reach:(c + 1) * PPC + reach]


def has(pixels: np.ndarray, bgr: tuple[int, int, int], tolerance: int = 0) -> bool:
    """Whether a pixel is ``bgr`` (each channel within ``tolerance``: anti-aliased lines)."""
    return bool((np.abs(pixels.astype(int) - bgr) <= tolerance).all(axis=-1).any())


def colour(value: float) -> np.ndarray:
    """The heat-map colour of a normalised value."""
    return cv2.applyColorMap(np.array([[round(value * 255)]], np.uint8), render.COLORMAP)[0, 0]


def heat(bgr: np.ndarray) -> int:
    """How hot a colour is: its level (0-255) in the colour map, by the nearest colour."""
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], render.COLORMAP)[:, 0]
    return int(np.argmin(np.abs(lut.astype(int) - np.asarray(bgr, int)).sum(axis=1)))


def test_full_picture_has_one_square_per_cell_and_base_colours() -> None:
    image = render_map(snapshot(objects=()), crop=False, px_per_cell=PPC, legend=False)
    assert image.dtype == np.uint8 and image.shape == (ROWS * PPC, COLS * PPC, 3)
    with_legend = render_map(snapshot(objects=()), crop=False, px_per_cell=PPC)  # the legend to its right
    assert with_legend.shape == (ROWS * PPC, COLS * PPC + render.LEGEND_WIDTH, 3)
    np.testing.assert_array_equal(with_legend[:, :COLS * PPC], image)
    assert tuple(pixel(image, (10, 10))) == render.UNEXPLORED
    assert tuple(pixel(image, (52, 148))) == render.FREE
    assert tuple(pixel(image, POST)) == render.OBSTACLE == (0, 0, 0)
    assert tuple(pixel(image, (WALL_ROW, 145))) == render.OBSTACLE


def test_image_up_is_plus_y() -> None:
    obstacle = np.zeros((ROWS, COLS), bool)
    obstacle[ROWS - 1, 0] = True  # the cell with the largest y, smallest x: top left
    image = render_map(snapshot(obstacle=obstacle), crop=False, px_per_cell=PPC)
    assert (image[:PPC, :PPC] == 0).all()
    assert not (image[-PPC:, :PPC] == 0).all()


def test_crop_keeps_the_explored_area_and_a_margin() -> None:
    full = render_map(snapshot(objects=()), crop=False, px_per_cell=PPC, legend=False)
    image = render_map(snapshot(objects=()), px_per_cell=PPC, legend=False)
    r0, r1, c0, c1 = CROP
    assert image.shape == ((r1 - r0) * PPC, (c1 - c0) * PPC, 3)
    assert image.shape[0] < full.shape[0] and image.shape[1] < full.shape[1]
    for cell in (POST, HOT, (52, 148), (r0, c0)):
        np.testing.assert_array_equal(pixel(image, cell, CROP), pixel(full, cell))


def test_crop_grows_to_show_a_robot_outside_the_explored_area() -> None:
    robot_cell = (150, 250)
    x, y = centre(robot_cell)
    image = render_map(snapshot(), robot=(x, y, 0.0), px_per_cell=PPC, legend=False)
    crop = (CROP[0], robot_cell[0] + 1 + MARGIN, CROP[2], robot_cell[1] + 1 + MARGIN)
    assert image.shape[:2] == ((crop[1] - crop[0]) * PPC, (crop[3] - crop[2]) * PPC)
    assert tuple(pixel(image, (robot_cell[0], robot_cell[1] - 2), crop)) == render.ROBOT


def test_nothing_explored_shows_the_whole_grid() -> None:
    empty = np.zeros((ROWS, COLS), bool)
    image = render_map(snapshot(explored=empty, obstacle=empty, objects=(),
                                frontiers=np.empty((0, 2))), px_per_cell=1, legend=False)
    assert image.shape == (ROWS, COLS, 3)
    assert (image == render.UNEXPLORED).all()


def test_a_high_value_cell_is_hotter_than_a_low_one() -> None:
    image = render_map(snapshot(), layer="cup", crop=False, px_per_cell=PPC)
    hot, warm = pixel(image, HOT), pixel(image, WARM)
    np.testing.assert_array_equal(hot, colour(1.0))
    np.testing.assert_array_equal(warm, colour(0.2))
    assert heat(hot) == 255 and heat(warm) == 51


def test_one_layer_by_name_or_the_normalised_sum_of_all() -> None:
    bed = render_map(snapshot(), layer="bed", crop=False, px_per_cell=PPC)
    np.testing.assert_array_equal(pixel(bed, WARM), colour(1.0))
    assert tuple(pixel(bed, HOT)) == render.FREE  # no bed value there: plain free floor
    # Sum of per-layer normalised values: HOT 1 + 0, WARM 0.2 + 1; shown divided by 1.2.
    total = value_image(snapshot())
    assert total[HOT] == pytest.approx(1 / 1.2) and total[WARM] == pytest.approx(1.0)
    both = render_map(snapshot(), crop=False, px_per_cell=PPC)
    np.testing.assert_array_equal(pixel(both, HOT), colour(float(total[HOT])))
    assert heat(pixel(both, WARM)) > heat(pixel(both, HOT))


def test_values_on_obstacles_and_unexplored_cells_are_not_painted() -> None:
    snap = snapshot()
    snap.values[0][POST] = 9.0
    snap.values[0][10, 10] = 9.0
    image = render_map(snap, layer="cup", crop=False, px_per_cell=PPC)
    assert tuple(pixel(image, POST)) == render.OBSTACLE
    assert tuple(pixel(image, (10, 10))) == render.UNEXPLORED


def test_an_unknown_layer_is_refused_with_the_known_names() -> None:
    with pytest.raises(ValueError, match=r"'sofa'.*'cup', 'bed'"):
        render_map(snapshot(), layer="sofa")


def test_no_layers_at_all_still_renders() -> None:
    snap = snapshot(layers=(), values=np.zeros((0, ROWS, COLS), np.float32), counts=np.zeros((0, ROWS, COLS), np.uint16))
    image = render_map(snap, crop=False, px_per_cell=PPC)
    assert tuple(pixel(image, HOT)) == render.FREE


def test_robot_is_a_disc_with_a_heading_line() -> None:
    x, y = centre(ROBOT_CELL)
    behind = (ROBOT_CELL[0], ROBOT_CELL[1] - 2)  # 0.1 m behind the centre: inside the disc
    ahead = (ROBOT_CELL[0], ROBOT_CELL[1] + 5)   # 0.25 m ahead: on the heading line only
    without = render_map(snapshot(), crop=False, px_per_cell=PPC)
    image = render_map(snapshot(), robot=(x, y, 0.0), crop=False, px_per_cell=PPC)
    assert tuple(pixel(without, behind)) == render.FREE
    assert tuple(pixel(image, behind)) == render.ROBOT
    assert pixel(image, ahead).max() < 60  # the black heading line
    turned = render_map(snapshot(), robot=(x, y, math.pi / 2), crop=False, px_per_cell=PPC)
    assert pixel(turned, (ROBOT_CELL[0] + 5, ROBOT_CELL[1])).max() < 60  # now it points up (+y)
    assert tuple(pixel(turned, ahead)) == render.FREE


def test_path_frontiers_and_objects_are_drawn() -> None:
    a, b = centre((52, 102)), centre((52, 122))
    base = render_map(snapshot(objects=(), frontiers=np.empty((0, 2))), crop=False, px_per_cell=PPC)
    image = render_map(snapshot(), path=[a, b], crop=False, px_per_cell=PPC)
    assert tuple(pixel(base, (52, 112))) == render.FREE
    assert tuple(pixel(image, (52, 112))) != render.FREE  # the path crosses this cell
    diff = np.any(image != base, axis=2)
    r, c = FRONTIER_CELL
    assert diff[(ROWS - 1 - r) * PPC - 4:(ROWS - r) * PPC + 4, c * PPC - 4:(c + 1) * PPC + 4].any()
    # Confirmed: a green ring; unconfirmed: an orange ring (as the page draws them); hollow both.
    cup, bed = around(image, CUP_CELL), around(image, BED_CELL)
    assert tuple(pixel(image, CUP_CELL)) == render.FREE and tuple(pixel(image, BED_CELL)) == render.FREE
    assert has(cup, render.CONFIRMED) and not has(cup, render.UNCONFIRMED)
    assert has(bed, render.UNCONFIRMED) and not has(bed, render.CONFIRMED)


def test_px_per_cell_must_be_positive() -> None:
    with pytest.raises(ValueError, match="px_per_cell"):
        render_map(snapshot(), px_per_cell=0)


def test_write_png_round_trips_and_leaves_no_temporary_file(tmp_path) -> None:
    image = render_map(snapshot())
    out = write_png(tmp_path / "map.png", image)
    assert out == tmp_path / "map.png"
    np.testing.assert_array_equal(cv2.imread(str(out)), image)
    write_png(out, image[::2, ::2])  # replacing an existing picture
    assert cv2.imread(str(out)).shape == image[::2, ::2].shape
    assert [p.name for p in tmp_path.iterdir()] == ["map.png"]


def test_write_png_into_a_missing_directory_fails_clearly(tmp_path) -> None:
    with pytest.raises(OSError):
        write_png(tmp_path / "nope" / "map.png", render_map(snapshot()))
    with pytest.raises(ValueError, match="cannot encode"):
        write_png(tmp_path / "map.png", np.zeros((0, 0, 3), np.uint8))


def test_the_picture_shows_the_decayed_map_the_planner_decides_on() -> None:
    from ovamos.services.planner.decide import DecisionConfig, decision_values, explored_window

    counts = np.zeros((2, ROWS, COLS), np.uint16)
    counts[:, HOT[0], HOT[1]] = 12    # looked at twice tau times: nearly faded
    counts[:, WARM[0], WARM[1]] = 3
    snap = snapshot(counts=counts)
    rows, cols, _ = explored_window(snap)
    planner = decision_values(snap, ["cup", "bed"], DecisionConfig(), (rows, cols))
    shown = value_image(snap)
    np.testing.assert_allclose(shown[rows, cols], planner / planner.max(), rtol=1e-6)
    assert shown[HOT] < 0.1 < shown[WARM] == pytest.approx(1.0)  # raw values: HOT 1/1.2 of WARM
    assert (shown[:rows.start] == 0).all() and (shown[rows.stop:] == 0).all()


# -- issue 32: legend, robot heading, label placement, the task's own detections ------------------
def overlaps(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def test_the_legend_beside_the_map_says_what_every_colour_and_mark_means() -> None:
    names = " | ".join(name for name, _ in render.LEGEND)
    for meaning in ("unexplored", "free", "obstacle", "value", "frontier", "goal", "path", "robot",
                    "heading", "detection, confirmed", "detection, unconfirmed", "found", "other task"):
        assert meaning in names, meaning
    image = render_map(snapshot(), crop=False, px_per_cell=PPC)
    panel = image[:, COLS * PPC:]
    assert panel.shape[1] == render.LEGEND_WIDTH
    for bgr in (render.UNEXPLORED, render.FREE, render.OBSTACLE, render.FRONTIER, render.PATH,
                render.ROBOT, render.GOAL, render.CONFIRMED, render.UNCONFIRMED, render.FOUND,
                render.OTHER, tuple(colour(0.0)), tuple(colour(1.0))):
        assert has(panel, bgr, tolerance=20), bgr
    assert has(panel, render.INK)  # the names, written in the legend's ink


def test_a_map_smaller_than_its_legend_is_padded_below_not_cut() -> None:
    explored = np.zeros((ROWS, COLS), bool)
    explored[60:64, 120:124] = True
    image = render_map(snapshot(explored=explored, obstacle=np.zeros((ROWS, COLS), bool), objects=(),
                                frontiers=np.empty((0, 2))), px_per_cell=1, margin_cells=2)
    rows = 2 + len(render.LEGEND)
    assert image.shape[0] >= rows * render.LEGEND_ROW and image.shape[1] == 8 + render.LEGEND_WIDTH
    assert tuple(image[-1, 0]) == render.PANEL  # below the 8 x 8 map: plain background


@pytest.mark.parametrize("ppc", [1, 2, 3])
@pytest.mark.parametrize("yaw", [0.0, math.pi / 2, math.pi, -3 * math.pi / 4])
def test_the_robot_is_a_disc_with_a_heading_arrow_that_stands_out_at_the_pictures_scale(ppc, yaw) -> None:
    x, y = centre((65, 125))  # 10 cells from the explored patch's edges
    image = render_map(snapshot(objects=(), frontiers=np.empty((0, 2))), robot=(x, y, yaw), crop=False,
                       px_per_cell=ppc, legend=False)
    u, v = (x - X0) / RES * ppc, ROWS * ppc - (y - Y0) / RES * ppc
    radius = max(5, round(0.18 * ppc / RES))
    dx, dy = math.cos(yaw), -math.sin(yaw)

    def at(distance: float) -> np.ndarray:
        return image[math.floor(v + dy * distance), math.floor(u + dx * distance)]

    assert tuple(at(-(radius - 2))) == render.ROBOT  # behind the centre: the disc, >= 5 px across
    beyond = [at(radius + d).max() for d in range(2, 9)]
    assert max(beyond) < 60, beyond  # >= 7 px of dark arrow out of the disc, along the heading
    su, sv = math.floor(u + dx * (radius + 5)), math.floor(v + dy * (radius + 5))
    assert has(image[sv - 3:sv + 4, su - 3:su + 4], (255, 255, 255), 10)  # the arrow's white edge
    assert tuple(at(-(radius + 5))) == render.FREE  # nothing out of the disc behind it


def test_only_objects_of_the_tasks_targets_are_drawn_as_its_detections() -> None:
    # the map kept a sofa of an earlier task; this one searches for the cup and the bed
    sofa_cell = (65, 130)
    sofa = ObjectInstance(label="sofa", x=centre(sofa_cell)[0], y=centre(sofa_cell)[1], score=0.9,
                          hits=9, confirmed=True)
    snap = snapshot(objects=(*snapshot().objects, sofa))
    image = render_map(snap, crop=False, px_per_cell=PPC)  # targets: the layers, cup and bed
    assert has(around(image, CUP_CELL), render.CONFIRMED)
    assert has(around(image, BED_CELL), render.UNCONFIRMED)
    grey = around(image, sofa_cell)
    assert has(grey, render.OTHER) and not has(grey, render.CONFIRMED) and not has(grey, render.UNCONFIRMED)
    # the task's own target list wins over the layers: a task for the bed only
    bed_only = render_map(snap, targets=["bed"], crop=False, px_per_cell=PPC)
    assert has(around(bed_only, CUP_CELL), render.OTHER) and not has(around(bed_only, CUP_CELL), render.CONFIRMED)
    assert has(around(bed_only, BED_CELL), render.UNCONFIRMED)


def test_a_found_target_whose_layer_is_gone_stays_this_tasks_and_is_a_green_square() -> None:
    from ovamos.shared.messages import FoundObject

    # the cup was found: the mapping service dropped its layer; its object is still on the map
    snap = snapshot(layers=("bed",), values=snapshot().values[1:], counts=snapshot().counts[1:])
    x, y = centre(CUP_CELL)
    found = [FoundObject(label="cup", x=x, y=y, step=12)]
    without = render_map(snap, crop=False, px_per_cell=PPC)
    assert has(around(without, CUP_CELL), render.OTHER)  # no task known: the layers say "not ours"
    image = render_map(snap, found=found, crop=False, px_per_cell=PPC)
    assert tuple(pixel(image, CUP_CELL)) == render.FOUND
    assert not has(around(image, CUP_CELL), render.OTHER)
    assert has(around(image, CUP_CELL, reach=10), (255, 255, 255))  # the square's white edge


def test_the_goal_is_a_red_ring_and_the_crop_shows_it_and_the_found_targets() -> None:
    from ovamos.shared.messages import FoundObject, Goal

    goal_cell, found_cell = (120, 125), (20, 125)  # both outside the explored patch
    goal = Goal(kind="candidate", x=centre(goal_cell)[0], y=centre(goal_cell)[1])
    found = [FoundObject(label="cup", x=centre(found_cell)[0], y=centre(found_cell)[1], step=3)]
    image = render_map(snapshot(), goal=goal, found=found, px_per_cell=PPC, legend=False)
    crop = (found_cell[0] - MARGIN, goal_cell[0] + 1 + MARGIN, CROP[2], CROP[3])
    assert image.shape[:2] == ((crop[1] - crop[0]) * PPC, (crop[3] - crop[2]) * PPC)
    assert tuple(pixel(image, goal_cell, crop)) == render.GOAL  # the dot in the ring
    r0, r1, c0, _ = crop
    r, c = goal_cell
    ring = image[(r1 - 1 - r) * PPC - 14:(r1 - r) * PPC + 14, (c - c0) * PPC - 14:(c - c0 + 1) * PPC + 14]
    assert (ring == render.GOAL).all(axis=2).sum() > 40
    assert tuple(pixel(image, found_cell, crop)) == render.FOUND


def test_labels_in_a_crowded_spot_do_not_overlap_and_stay_inside_the_picture() -> None:
    width, height = 300, 200
    rng = np.random.default_rng(3)
    anchors = [(290 + rng.uniform(-8, 8), 8 + rng.uniform(-6, 6)) for _ in range(30)]  # a corner
    sizes = [(int(rng.integers(30, 80)), 14) for _ in anchors]
    marks = [(int(u) - 6, int(v) - 6, int(u) + 7, int(v) + 7) for u, v in anchors]
    rects = render.place_labels(anchors, sizes, (width, height), avoid=marks)
    assert all(r is not None for r in rects)
    for i, (rect, (w, h)) in enumerate(zip(rects, sizes)):
        assert rect[2] - rect[0] == w and rect[3] - rect[1] == h
        assert 0 <= rect[0] and 0 <= rect[1] and rect[2] <= width and rect[3] <= height, rect
        assert not any(overlaps(rect, other) for other in rects[i + 1:]), i
        assert not any(overlaps(rect, m) for m in marks), i
    # a label goes beside its mark when there is room: right of it, vertically centred
    (alone,) = render.place_labels([(50, 100)], [(40, 14)], (width, height))
    assert alone == (56, 93, 96, 107)
    # no room at all: None, and the others still do not overlap
    packed = render.place_labels([(50, 20)] * 8, [(40, 14)] * 8, (100, 40))
    assert None in packed
    placed = [r for r in packed if r is not None]
    assert placed and not any(overlaps(a, b) for i, a in enumerate(placed) for b in placed[i + 1:])


def test_the_pictures_labels_do_not_overlap_stay_on_the_map_and_none_is_lost(monkeypatch) -> None:
    drawn: list[tuple[str, tuple[int, int, int, int]]] = []
    listed: list[str] = []
    draw_label, legend = render._draw_label, render._legend

    def record_label(image, text, rect, colour):
        drawn.append((text, rect))
        draw_label(image, text, rect, colour)

    def record_legend(height, targets, layer, lines):
        listed.extend(lines)
        return legend(height, targets, layer, lines)

    monkeypatch.setattr(render, "_draw_label", record_label)
    monkeypatch.setattr(render, "_legend", record_legend)
    edge = (70, 150)  # the explored patch's right edge: the crop ends MARGIN cells further
    x, y = centre(edge)
    crowd = tuple(ObjectInstance(label=("cup", "bed", "lamp")[i % 3], x=x - 0.02 * (i % 3), y=y + 0.02 * (i // 3),
                                 score=0.5, hits=i + 1, confirmed=i % 2 == 0) for i in range(18))
    image = render_map(snapshot(objects=crowd), robot=(x - 0.2, y, 0.0), px_per_cell=PPC)
    width = (CROP[3] - CROP[2]) * PPC  # the map's part of the picture (the legend is right of it)
    height = (CROP[1] - CROP[0]) * PPC
    assert image.shape[1] == width + render.LEGEND_WIDTH
    rects = [rect for _, rect in drawn]
    for i, rect in enumerate(rects):
        assert 0 <= rect[0] and 0 <= rect[1] and rect[2] <= width and rect[3] <= height, drawn[i]
        assert not any(overlaps(rect, other) for other in rects[i + 1:]), drawn[i]
    # every detection of the task's targets is labelled on the map or listed in the legend by the
    # number drawn at it; the lamps (no target) are grey and may go unlabelled
    ours = sorted(f"{o.label} x{o.hits}" for o in crowd if o.label != "lamp")
    on_map = [text for text, _ in drawn]
    numbered = [line.split(" ", 1) for line in listed]
    assert numbered  # 12 labels in a spot this small: some are numbers on the map
    assert sorted([t for t in on_map if t in ours] + [text for _, text in numbered]) == ours
    assert all(n in on_map for n, _ in numbered)
    assert all(t in ours or t == "lamp" or t.isdigit() for t in on_map)
