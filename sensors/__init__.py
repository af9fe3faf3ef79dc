"""Sensor drivers: bus I/O and decoding only.

Drivers never start threads, keep queues or read clocks for time stamps: the sampler threads in
``logger`` own timing, retries and reconnects, so a driver can be driven by a test one call at a time.
"""
