"""Recording, replay and live view (``ovamos record | replay | view``).

The cores here know nothing of Zenoh: :mod:`.channels` (which keys are recorded, and their raw
MCAP channels, from :data:`ovamos.shared.topology.TOPOLOGY`), :mod:`.views` (messages drawn in
Foxglove's well-known schemas), :mod:`.recorder` (a byte-bounded queue in front of an MCAP
writer) and :mod:`.replay` (reading raw channels back, with their timing). :mod:`.live` is the
thin adapter that wires them to a robot's keys.
"""
