"""mapsqueeze: learned compression of dense 3-D LiDAR point-cloud maps."""

__version__ = "0.1.0"
