"""Message types for reading ROS bags without running anything a bag carries.

rosbags' ``AnyReader`` turns the message definitions stored in a bag into Python source and
``exec`` s it (``Typestore.register``): a crafted bag could put text there that becomes code.
rosbags' own grammar rejects the obvious injections today, but treeinfer should not depend on
that, and it needs only a handful of standard types. So :func:`open_bag_reader`:

1. validates every connection's message type name and topic as ROS identifiers *before*
   anything else (a name like ``pkg/msg/X(__import__('os')...)`` is refused, naming the topic);
2. never parses the bag's own definitions: it decodes with rosbags' *built-in* stores (ROS 1
   Noetic or ROS 2 Humble, shipped as Python modules), plus ``tf2_msgs/msg/TFMessage`` from
   the fixed definition below when the store lacks it;
3. checks each known type the bag uses against the built-in definition's hash (ROS 1 md5,
   ROS 2 RIHS01) where the bag records one, so a bag whose ``WrenchStamped`` is laid out
   differently is refused instead of decoded into garbage.

Connections of other types stay listed (topic auto-detection names them) but are never decoded.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import TrajectoryFileError

__all__ = ["KNOWN_TYPES", "open_bag_reader", "valid_msgtype", "valid_topic"]

KNOWN_TYPES = (
    "geometry_msgs/msg/WrenchStamped",
    "geometry_msgs/msg/Wrench",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/Transform",
    "tf2_msgs/msg/TFMessage",
)
# tf2_msgs is not in the Noetic store; this fixed text (not the bag's) defines it.
_TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms"

_IDENT = r"[A-Za-z][A-Za-z0-9_]*"
_MSGTYPE = re.compile(rf"^{_IDENT}(/{_IDENT})?/{_IDENT}$")
_TOPIC = re.compile(r"^/?[A-Za-z0-9_~{}][A-Za-z0-9_/~{}]*$")


def valid_msgtype(name: str) -> bool:
    """``pkg/Type`` or ``pkg/msg/Type`` made of ROS identifiers (letters, digits, ``_``)."""
    return isinstance(name, str) and len(name) < 256 and bool(_MSGTYPE.match(name))


def valid_topic(name: str) -> bool:
    return isinstance(name, str) and len(name) < 1024 and bool(_TOPIC.match(name))


def _builtin_store(is2: bool):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE if is2 else Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        from rosbags.typesys import get_types_from_msg

        ts.register(get_types_from_msg(_TF_MESSAGE_DEF, "tf2_msgs/msg/TFMessage"))
    return ts


def _reader_class():
    from rosbags.highlevel import AnyReader

    class _KnownTypesReader(AnyReader):
        """AnyReader whose typestore comes from rosbags' built-in stores, never from the bag."""

        def _open(self) -> None:
            assert self.stack
            for reader in self.readers:
                self.stack.enter_context(reader)
            connections = [c for r in self.readers for c in r.connections]
            for c in connections:
                if not valid_topic(c.topic):
                    raise TrajectoryFileError(
                        f"{self.paths[0]}: topic name {c.topic[:80]!r} is not a valid ROS topic; "
                        "refusing a bag that may have been crafted"
                    )
                if not valid_msgtype(c.msgtype):
                    raise TrajectoryFileError(
                        f"{self.paths[0]}: topic {c.topic}: message type "
                        f"{c.msgtype[:80]!r} is not a "
                        "valid ROS type name; refusing a bag that may have been crafted"
                    )
            ts = _builtin_store(self.is2)
            for c in connections:
                if c.msgtype not in KNOWN_TYPES or not c.digest:
                    continue
                digest = str(c.digest)
                if self.is2:
                    if not digest.startswith("RIHS01_"):
                        continue
                    have = ts.hash_rihs01(c.msgtype)
                else:
                    have = ts.generate_msgdef(c.msgtype)[1]
                if have != digest:
                    raise TrajectoryFileError(
                        f"{self.paths[0]}: topic {c.topic}: the bag's definition of {c.msgtype} "
                        f"differs from the standard one (hash {digest[:20]}..., expected "
                        f"{have[:20]}...); treeinfer decodes only the standard message types"
                    )
            self.connections = connections
            self.typestore = ts

    return _KnownTypesReader


def open_bag_reader(bag: str | Path):
    """An opened rosbags ``AnyReader`` for ``bag`` whose types come only from rosbags'
    built-in stores (see the module docstring); the caller closes it.

    Raises:
      TrajectoryFileError: unreadable bag, invalid type or topic names, or a known type with a
        non-standard definition.
    """
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2

    bag = Path(bag)
    from ..io.safe_load import refuse_special_paths

    refuse_special_paths(bag, "bag", TrajectoryFileError)  # a FIFO would block the reader
    try:
        reader = _reader_class()([bag])
        reader.open()
    except TrajectoryFileError:
        raise
    except (AnyReaderError, ReaderError1, ReaderError2, OSError, ValueError, KeyError) as e:
        raise TrajectoryFileError(f"{bag}: cannot read as a ROS1 or ROS2 bag ({e})") from None
    return reader
