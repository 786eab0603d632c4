"""Exceptions raised by the bag helpers (one class per kind of bad input)."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class BagError(PiezoStageError):
    """Base class of every error raised by ``piezo_stage.bag``."""


class BagNotFoundError(BagError, FileNotFoundError):
    """The path is neither a rosbag2 folder with MCAP files nor a ``.mcap`` file."""


class BagExistsError(BagError, FileExistsError):
    """The writer would overwrite an existing, non-empty bag folder."""


class BagClosedError(BagError):
    """The writer was used after ``close()``."""


class UnknownTopicError(BagError, KeyError):
    """A topic was written or asked for that the bag does not hold."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


class DuplicateTopicError(BagError, ValueError):
    """``add_topic`` was called twice for one topic with different types."""


class UnknownMessageTypeError(BagError, KeyError):
    """A message type is neither in the typestore nor findable as a ``.msg`` file."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class InvalidQosError(BagError, ValueError):
    """An offered QoS profile is malformed (unknown policy name or missing field)."""


class WrongTopicTypeError(BagError, TypeError):
    """A topic exists but has a type the operation cannot handle."""


class CorruptBagError(BagError):
    """An MCAP file is damaged beyond what the tolerant reader recovers."""


class BagDamageWarning(UserWarning):
    """An MCAP file has CRC or record errors: some messages were not read (counts in text)."""


class SkippedTopicWarning(UserWarning):
    """A topic was left out because its messages cannot be decoded (reason in text)."""
