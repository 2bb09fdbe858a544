"""The base driver: ODrive CANSimple motor controllers over python-can, odometry, primitives, safety."""
