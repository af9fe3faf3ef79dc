"""Device models of the four sensors and the PPS line, behind the same buses as the hardware.

Models sit at the bus (SMBus ioctl, the master side of a pty, a python-can virtual bus, gpiod-shaped edge
events), so the drivers above them cannot tell them from the chips. They are driven by a vehicle truth
model and a clock of the simulated drive, both seeded, so every run can be repeated and scored.
"""
