"""The TurtleBot 3 base (OpenCR board): Dynamixel 2.0, the control table, the hardware interface, a simulated board."""
