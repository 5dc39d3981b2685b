"""Typed errors of orchard_mapping, one family per area.

Library code raises these with context (which bag, topic, frame, field);
only the CLI maps them to messages and exit codes.
"""

from __future__ import annotations


class OrchardMappingError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(OrchardMappingError):
    """A configuration file or value is invalid (the message names the key)."""


class BagError(OrchardMappingError):
    """A bag cannot be used. `bag` and `topic` say where."""

    def __init__(self, message: str, *, bag: str | None = None, topic: str | None = None) -> None:
        where = ", ".join(p for p in (f"bag {bag}" if bag else "", f"topic {topic}" if topic else "") if p)
        super().__init__(f"{message} ({where})" if where else message)
        self.bag = bag
        self.topic = topic


class BagReadError(BagError):
    """The file or folder is missing or unreadable as rosbag2 / MCAP."""


class EmptyBagError(BagError):
    """The bag holds no messages (on the topics asked for)."""


class MissingTopicError(BagError):
    """A required topic is not in the bag."""


class BagFormatError(BagError):
    """A message's content is unusable: unknown encoding, wrong size, bad field."""


class CalibrationError(BagError):
    """Camera intrinsics are missing or invalid (zero focal length, ...)."""


class ScenarioError(OrchardMappingError):
    """A simulator scenario is unknown or invalid."""


class GroundTruthError(OrchardMappingError):
    """A ground-truth file is missing, unreadable or of the wrong schema."""


class ResultFormatError(OrchardMappingError):
    """A result folder does not follow the result contract (docs/results.md)."""


class OutputError(OrchardMappingError):
    """The result folder cannot be written (no permission, not a folder, disk full). `path` says where; an
    earlier result in the folder is left as it was."""

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"{message} (folder {path})")
        self.path = path


class AlignmentError(OrchardMappingError):
    """Two reconstructions (or a trajectory and its reference) cannot be aligned."""


class MergeRefusedError(AlignmentError):
    """`orchard-map run` could not merge the two sides. Each side's own results (trajectories, clouds,
    trunks, grounds) were written; nothing of the merge was (no side_merge.json, no trees in map)."""
