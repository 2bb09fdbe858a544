"""The errors of perception backends, in a module of their own so that the backend interface
(:mod:`.backend`) and the backends (:mod:`.sim_backend`, :mod:`.hf`) import them without
importing each other."""

from __future__ import annotations

from ovamos.shared.config import ServiceConfigError

__all__ = ["BackendError", "FrameRejected"]


class FrameRejected(ValueError):
    """This frame cannot be processed by this backend (the input's fault, not the backend's)."""


class BackendError(ServiceConfigError):
    """A backend that cannot start with its config (model directories missing or incomplete,
    torch absent, a scene that cannot be loaded): ``ovamos run`` prints it as a config error."""
