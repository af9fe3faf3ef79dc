"""What an MPU-6050 answers in WHO_AM_I, and what other chips at its address answer.

Kept apart from the driver (which needs numpy) so that the configuration's check of ``[imu] who_am_i`` costs
``logger status`` and ``logger config-check`` no import of it.
"""

from __future__ import annotations

WHO_AM_I_VALUE = 0x68  # the MPU-6050's, whatever its AD0 address

# Other InvenSense parts: another FIFO size, temperature scale and register map, which the driver does not know.
OTHER_PARTS = {0x70: "an MPU-6500", 0x71: "an MPU-9250", 0x73: "an MPU-9255"}

# What GY-521 boards' clones of the MPU-6050 answer (0x98 is common, 0x72 is reported): they work as one, and the
# driver takes them once their owner says so (``[imu] who_am_i``).
CLONE_WHO_AM_I = (0x98, 0x72)
