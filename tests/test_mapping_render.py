"""Map pictures: a hand-built snapshot whose every cell is known, read back pixel by pixel."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from services.mapping import render
from services.mapping.render import render_map, value_image, write_png
from shared.messages import MapSnapshot, ObjectInstance

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


def colour(value: float) -> np.ndarray:
    """The heat-map colour of a normalised value."""
    return cv2.applyColorMap(np.array([[round(value * 255)]], np.uint8), render.COLORMAP)[0, 0]


def heat(bgr: np.ndarray) -> int:
    """How hot a colour is: its level (0-255) in the colour map, by the nearest colour."""
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], render.COLORMAP)[:, 0]
    return int(np.argmin(np.abs(lut.astype(int) - np.asarray(bgr, int)).sum(axis=1)))


def test_full_picture_has_one_square_per_cell_and_base_colours() -> None:
    image = render_map(snapshot(), crop=False, px_per_cell=PPC)
    assert image.dtype == np.uint8 and image.shape == (ROWS * PPC, COLS * PPC, 3)
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
    full = render_map(snapshot(), crop=False, px_per_cell=PPC)
    image = render_map(snapshot(), px_per_cell=PPC)
    r0, r1, c0, c1 = CROP
    assert image.shape == ((r1 - r0) * PPC, (c1 - c0) * PPC, 3)
    assert image.shape[0] < full.shape[0] and image.shape[1] < full.shape[1]
    for cell in (POST, HOT, (52, 148), (r0, c0)):
        np.testing.assert_array_equal(pixel(image, cell, CROP), pixel(full, cell))


def test_crop_grows_to_show_a_robot_outside_the_explored_area() -> None:
    robot_cell = (150, 250)
    x, y = centre(robot_cell)
    image = render_map(snapshot(), robot=(x, y, 0.0), px_per_cell=PPC)
    crop = (CROP[0], robot_cell[0] + 1 + MARGIN, CROP[2], robot_cell[1] + 1 + MARGIN)
    assert image.shape[:2] == ((crop[1] - crop[0]) * PPC, (crop[3] - crop[2]) * PPC)
    assert tuple(pixel(image, (robot_cell[0], robot_cell[1] - 2), crop)) == render.ROBOT


def test_nothing_explored_shows_the_whole_grid() -> None:
    empty = np.zeros((ROWS, COLS), bool)
    image = render_map(snapshot(explored=empty, obstacle=empty, objects=(),
                                frontiers=np.empty((0, 2))), px_per_cell=1)
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
    # Confirmed: a filled green square; unconfirmed: a hollow orange ring.
    assert tuple(pixel(image, CUP_CELL)) == render.CONFIRMED
    assert tuple(pixel(image, BED_CELL)) == render.FREE
    r, c = BED_CELL
    ring = image[(ROWS - 1 - r) * PPC - 6:(ROWS - r) * PPC + 6, c * PPC - 6:(c + 1) * PPC + 6]
    assert (ring == render.UNCONFIRMED).all(axis=2).any()
    assert not (ring == render.CONFIRMED).all(axis=2).any()


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
    from services.planner.decide import DecisionConfig, decision_values, explored_window

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
