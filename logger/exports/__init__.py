"""What a drive becomes at the office: tracks, GPX/KML/CSV, plots, topic timing."""
