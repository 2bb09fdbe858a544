"""The base driver: one controller over a hardware interface, and a subpackage per base it drives."""
