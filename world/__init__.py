"""The simulated world: scenes (homes of rooms, walls and objects) and their generation, the object
prior, rendering a camera's view, the simulated perception model, the ground truth that judges a
STOP, and the benchmark's episodes. A library, not a service: the ``sim`` service
(:mod:`ovamos.services.sim`) drives a robot through it, perception's simulated backend labels its
frames, the benchmark and the CLI build homes and episodes from it. It imports only
:mod:`ovamos.shared` (a contract in pyproject.toml)."""
