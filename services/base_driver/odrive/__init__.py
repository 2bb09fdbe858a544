"""The ODrive base (a custom CAN base): CANSimple over the DBC, the hardware interface, simulated axes."""
