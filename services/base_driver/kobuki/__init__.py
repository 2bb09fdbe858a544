"""The Kobuki (TurtleBot 2) base: its serial protocol, the hardware interface over it, a simulated Kobuki."""
