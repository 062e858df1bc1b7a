"""pipescan: pipe condition measured from LiDAR."""

__version__ = "0.1.0"
