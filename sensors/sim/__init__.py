"""Device models of the four sensors and the PPS line, behind the same buses as the hardware.

Models sit at the bus (SMBus ioctl, the master side of a pty, a python-can virtual bus, gpiod-shaped edge
events), so the drivers above them cannot tell them from the chips. They are driven by a vehicle truth
model and a clock of the simulated drive, both seeded, so every run can be repeated and scored.

A model never imports a driver (any module of :mod:`sensors` outside :mod:`sensors.sim`): it is the
datasheet's other side, written from the datasheet on its own, so a test of the driver against the model
catches a driver that misreads the datasheet instead of sharing its mistake. Register maps, constants,
checksums and compensation formulas a model needs therefore live in the model, even where a driver has
the same ones; ``tests/test_sim_basics.py`` checks every module's imports.
"""
