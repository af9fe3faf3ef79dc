"""Time synchronisation: PPS edges and GNSS time turned into a clock for every sample (no ``logger`` import)."""
