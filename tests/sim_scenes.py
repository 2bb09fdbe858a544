"""Hand-made scenes for simulator tests (sizes chosen so distances are easy to reason about)."""

from __future__ import annotations

from ovamos.world.scene import Room, Scene, SceneObject, Wall

GREY = (0.5, 0.5, 0.5, 1.0)


def two_rooms() -> Scene:
    """6 x 4 m house split at x = 3 by a wall with a 1 m doorway at y in [1.5, 2.5].

    Room 0 (kitchen, x < 3) has a fridge against the west wall; room 1 (office,
    x > 3) has a table with a cup on it and a second fridge, east wall.
    """
    return Scene(
        seed=None, width=6.0, depth=4.0,
        rooms=(Room(id=0, type="kitchen", x0=0, y0=0, x1=3, y1=4),
               Room(id=1, type="office", x0=3, y0=0, x1=6, y1=4)),
        walls=(Wall(x0=0, y0=0, x1=6, y1=0), Wall(x0=6, y0=0, x1=6, y1=4),
               Wall(x0=6, y0=4, x1=0, y1=4), Wall(x0=0, y0=4, x1=0, y1=0),
               Wall(x0=3, y0=0, x1=3, y1=1.5), Wall(x0=3, y0=2.5, x1=3, y1=4)),
        objects=(SceneObject(id=1, cls="fridge", x=0.4, y=3.0, z=0, sx=0.7, sy=0.7, sz=1.8,
                             room=0, rgba=GREY),
                 SceneObject(id=2, cls="table", x=4.5, y=1.0, z=0, sx=1.2, sy=0.8, sz=0.75,
                             room=1, rgba=GREY),
                 SceneObject(id=3, cls="cup", x=4.5, y=1.0, z=0.75, sx=0.08, sy=0.08, sz=0.1,
                             room=1, rgba=GREY, on=2),
                 SceneObject(id=4, cls="fridge", x=5.6, y=3.4, z=0, sx=0.7, sy=0.7, sz=1.8,
                             room=1, rgba=GREY)),
    )
