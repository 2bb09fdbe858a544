"""The HTTP gateway: people and scripts submit search tasks; the planner works on them over Zenoh."""
