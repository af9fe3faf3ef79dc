"""The logging daemon, its recorder, navigator, status server and command line."""
