"""The ``ovamos`` tool around the services: the command line, the process supervisor, deployment
profiles, the service registry and the demo. Nothing here is a service; it starts and watches them.

- :mod:`ovamos.cli`: the ``ovamos`` command (``run``, ``up``, ``demo``, ``graph``, ``bench`` ...).
- :mod:`ovamos.registry`: which services ``ovamos run`` can start (imported lazily).
- :mod:`ovamos.supervisor`: running processes, restarting crashed ones with backoff, the status table.
- :mod:`ovamos.profiles`: deployment profiles (``deploy/profiles/*.toml``) and ``ovamos up``'s supervisor.
- :mod:`ovamos.demo`: ``ovamos demo``, the whole system on one machine driven through its HTTP API.
"""

__version__ = "0.39.0"
