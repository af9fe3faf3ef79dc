"""The logging daemon and the ``logger`` command, in rooms: ``runtime`` (the daemon), ``recording`` (the file),
``nav`` (the filter), ``exports`` (the office), ``cli`` (the commands); ``compose`` builds a daemon from ``config``.
See docs/architecture.md."""

from __future__ import annotations

# The one place the version is written (pyproject.toml reads it): every recording's MCAP header names it
# (``library``: "vehicle-logger 0.2.0"), so the office can tell which release wrote a file. Files of 0.1.0 name none.
__version__ = "0.2.0"
