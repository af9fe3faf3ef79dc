"""The thread a simulated device answers on.

A real adapter or ECU answers on its own while the code under test waits on the bus: each model runs its loop
(``_run``, until ``stopping`` is set) beside it, started and stopped by the test or the simulated vehicle, or used
as a context manager.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from typing import Self


class DeviceThread(ABC):
    thread_name = "sim-device"

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> Self:
        if self._thread is None:
            self.stopping.clear()
            self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self.stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @abstractmethod
    def _run(self) -> None:
        """The device's loop: answer the bus until ``stopping`` is set."""
