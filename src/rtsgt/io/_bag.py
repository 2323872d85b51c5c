"""Opening ROS 1 / ROS 2 bags with ``rosbags`` (the ``bags`` extra; no ROS install).

One way to open a bag for every reader of bags (:mod:`rtsgt.io.trajectory`,
:mod:`rtsgt.io.rts_bag`): a ROS 1 ``.bag`` file, or a ROS 2 bag directory (with its
``metadata.yaml``) or its ``.db3`` / ``.mcap`` file, read by ``rosbags.highlevel.AnyReader``.
Message types come from the definitions the bag carries (ROS 1 bags always, ROS 2 bags from
Iron on); the types a reader registers (:func:`open_bag`'s ``types``) serve the bags that carry
none (ROS 2 before Iron). Every failure is an :class:`~rtsgt.errors.InputError` naming the bag.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from os import PathLike
from pathlib import Path

from rtsgt.errors import InputError

#: Suffixes of the files of a bag (ROS 1 file, ROS 2 storage files).
BAG_SUFFIXES = (".bag", ".db3", ".mcap")


def rosbags_modules():
    """``(AnyReader, Stores, get_typestore, get_types_from_msg)``, or an install hint."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as exc:
        raise InputError(
            "reading ROS bags needs the 'rosbags' package: pip install 'rtsgt[bags]'"
        ) from exc
    return AnyReader, Stores, get_typestore, get_types_from_msg


def bag_paths(path: str | PathLike) -> list[Path]:
    """The paths ``AnyReader`` takes for a bag given as its file or directory."""
    p = Path(path)
    if not p.exists():
        raise InputError("bag not found", p)
    if p.is_file() and p.suffix in (".db3", ".mcap") and (p.parent / "metadata.yaml").exists():
        return [p.parent]
    if p.is_dir() and not (p / "metadata.yaml").exists():
        raise InputError("a ROS 2 bag directory needs its metadata.yaml", p)
    return [p]


@contextmanager
def open_bag(path: str | PathLike, types: Mapping[str, str] | None = None) -> Iterator:
    """An open ``AnyReader`` of the bag at ``path``, closed on exit, with the message definitions
    ``types`` (``pkg/msg/Name`` -> ``.msg`` text) registered for connections whose bag lacks them.
    A missing ``rosbags`` or a bag it cannot open raises :class:`~rtsgt.errors.InputError`."""
    AnyReader, Stores, get_typestore, get_types_from_msg = rosbags_modules()
    store = get_typestore(Stores.LATEST)
    for name, text in (types or {}).items():
        store.register(get_types_from_msg(text, name))
    try:
        reader = AnyReader(bag_paths(path), default_typestore=store)
        reader.open()
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read the bag: {exc}", path) from exc
    try:
        yield reader
    finally:
        reader.close()
