"""orchard_mapping: semantic mapping of orchard rows from two-side reconstructions.

Layers (dependencies point down only): cli/ and ros/ -> pipeline/ -> core/ and io/; eval/ and sim/ beside
them (docs/architecture.md). `core` never imports rclpy or rosbags.
"""

__version__ = "0.1.0"
