"""The stage controller: the Grbl protocol, the pyserial driver, the motion model and the driver
of the simavr harness that runs the real firmware.

Depends only on `twin.core` (and the firmware's folder, for the harness); never on the simulator.
"""
