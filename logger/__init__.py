"""The logging daemon and the ``logger`` command, in rooms: ``runtime`` (the daemon), ``recording`` (the file),
``nav`` (the filter), ``exports`` (the office), ``cli`` (the commands); ``compose`` builds a daemon from ``config``.
See docs/architecture.md."""
