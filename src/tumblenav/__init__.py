"""tumblenav: relative navigation of a tumbling, non-cooperative spacecraft."""

__version__ = "0.1.0"
