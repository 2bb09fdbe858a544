"""Real perception models through transformers (the ``perception`` extra: torch, transformers, pillow).

Nothing here is imported by the base install: :func:`ovamos.services.perception.backend.load_backend`
imports :mod:`.backend` only when the config asks for ``backend = "hf"``.
"""
