"""Perception: RGB-D frames in, a value score per target and detections with masks out.

``backend`` is the interface every backend implements; ``sim_backend`` runs the
simulator's perception (tests, demo), ``hf`` the real models (BLIP / BLIP-2
ITM, GroundingDINO, SAM) through transformers, imported lazily so that the base
install needs no torch; ``errors`` holds what backends raise. ``core`` holds the service's
rules (targets per robot, batches, replica ownership; no bus), ``service`` wires the core and
a backend to the bus.
"""
