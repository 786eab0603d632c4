"""rosbag2/MCAP writing, reading, reindexing and export helpers. No rclpy.

Bags are rosbag2 folders (metadata version 9, MCAP storage, CDR messages, ``ros2msg``
schemas) that ``ros2 bag``, rosbags, the mcap library, Foxglove and PlotJuggler open.
"""

from .errors import (
    BagClosedError,
    BagDamageWarning,
    BagError,
    BagExistsError,
    BagNotFoundError,
    CorruptBagError,
    DuplicateTopicError,
    InvalidQosError,
    SkippedTopicWarning,
    UnknownMessageTypeError,
    UnknownTopicError,
    WrongTopicTypeError,
)
from .export import export_csv
from .info import bag_info, format_info
from .playback import PlaybackError
from .qos import LATCHED, RELIABLE, SENSOR_DATA, qos_from_profile, qos_profile
from .reader import loop_columns, read_loop_samples, read_messages, read_raw, read_series
from .reindex import reindex
from .types import (
    deserialize,
    header,
    message_class,
    message_definition,
    serialize,
    type_hash,
    typestore,
)
from .writer import BagWriter, InvalidBagOptionError, InvalidTopicNameError

__all__ = [
    "BagClosedError",
    "BagDamageWarning",
    "BagError",
    "BagExistsError",
    "BagNotFoundError",
    "BagWriter",
    "CorruptBagError",
    "DuplicateTopicError",
    "InvalidBagOptionError",
    "InvalidQosError",
    "InvalidTopicNameError",
    "LATCHED",
    "PlaybackError",
    "RELIABLE",
    "SENSOR_DATA",
    "SkippedTopicWarning",
    "UnknownMessageTypeError",
    "UnknownTopicError",
    "WrongTopicTypeError",
    "bag_info",
    "deserialize",
    "export_csv",
    "format_info",
    "header",
    "loop_columns",
    "message_class",
    "message_definition",
    "qos_from_profile",
    "qos_profile",
    "read_loop_samples",
    "read_messages",
    "read_raw",
    "read_series",
    "reindex",
    "serialize",
    "type_hash",
    "typestore",
]
