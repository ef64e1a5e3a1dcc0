"""DBC files as vehicles and vendors write them: several at once, loaded the way cantools loads them.

Why: a vehicle's DBC often has one odd message nobody uses (two signals overlapping, a signal
past the frame's end); refusing the whole file for it blocks the message the IMU does use. So
each file is loaded non-strictly, the messages that needed it are named once on stderr, and
only a message canical actually uses is refused for it (:func:`require_sound`, one line).
A user's IMU and vehicle come with several files, and canical's own frames (``CANICAL_RATE``,
``CANICAL_STATUS``, ``TABLE_REF``...) live in the shipped ``canical.dbc``: the files are merged,
the shipped one always beside them (only where the user's files do not define that name or id
themselves), and a name or id two files define differently is an error naming both files.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database, Message

from canical.errors import CanicalError

#: One DBC path, or several.
DbcPaths = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]

_WARNED: set[tuple[str, tuple[str, ...]]] = set()


def shipped_dbc_path() -> Path:
    """canical's own frames: the DBC shipped with the package (``dbc/canical.dbc`` in the source tree)."""
    return Path(str(resources.files("canical") / "data" / "canical.dbc"))


#: ``j1939.messages: all``: every extended-id message of the user's files is a J1939 parameter group.
ALL_EXTENDED = "all"


class DbcSet(tuple[Path, ...]):
    """Several DBC files where one path is expected: printed as their names, read by :func:`load_dbc`.

    Why a path-like: the readers that take one DBC path pass it on to :func:`load_dbc` and
    name it in their messages; given this, they read every file and name them all.

    It also carries which messages are J1939 parameter groups when the files do not say so
    (``j1939``: names, or :data:`ALL_EXTENDED`): a vendor's J1939 DBC often has neither the
    ``VFrameFormat`` nor the ``ProtocolType`` attribute cantools reads, and every reader that loads
    the files (the daemon, the log reader, ``record``) must match those messages by their PGN alike.
    """

    j1939: frozenset[str] = frozenset()

    def __new__(cls, paths: Iterable[Path], j1939: Iterable[str] = ()) -> DbcSet:
        made = super().__new__(cls, paths)
        made.j1939 = frozenset(j1939)
        return made

    def __str__(self) -> str:
        return " + ".join(str(p) for p in self)

    def __fspath__(self) -> str:
        return str(self[0])


def dbc_set(paths: DbcPaths) -> DbcSet:
    """The paths as a :class:`DbcSet`."""
    return DbcSet(dbc_list(paths))


def dbc_list(paths: DbcPaths) -> tuple[Path, ...]:
    """The paths as a tuple, whether one or several were given."""
    if isinstance(paths, DbcSet):
        return tuple(paths)
    if isinstance(paths, str | os.PathLike):
        return (Path(paths),)
    return tuple(Path(p) for p in paths)


def dbc_label(paths: DbcPaths) -> str:
    """The files' names for a message (``vendor.dbc + canical.dbc``)."""
    return " + ".join(p.name for p in dbc_list(paths))


def why_broken(message: Message) -> str | None:
    """Why cantools' strict check refuses the message (signals overlapping or past its end), or None."""
    try:
        message._check_signal_tree([None] * (8 * message.length), message.signal_tree)
    except Exception as exc:  # cantools.database.Error, or anything an odd tree raises
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


def require_sound(message: Message, what: str) -> None:
    """Refuse a message canical reads or writes when cantools could load it only non-strictly."""
    reason = why_broken(message)
    if reason is not None:
        raise CanicalError(f"{what}: message {message.name} is broken ({reason})")


def _load_one(path: Path) -> Database:
    name = str(path)
    if not path.is_file():
        raise CanicalError(f"{name}: DBC file not found")
    try:
        db = cantools.database.load_file(name, database_format="dbc", strict=False)
    except Exception as exc:  # cantools raises many types for a bad file
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanicalError(f"{name}: not a valid DBC file ({first})") from None
    loaded: Database = db  # type: ignore[assignment]  # a .dbc file loads as a CAN database
    for message in loaded.messages:
        _drop_undecoded(message)
    return loaded


def _tree_names(tree: Sequence[Any]) -> set[str]:
    """Every signal name in a cantools signal tree (multiplexers' branches included)."""
    names: set[str] = set()
    for node in tree:
        if isinstance(node, str):
            names.add(node)
            continue
        for mux, branches in node.items():
            names.add(mux)
            for branch in branches.values():
                names |= _tree_names(branch)
    return names


def _drop_undecoded(message: Message) -> None:
    """Leave out the signals cantools neither decodes nor encodes: signals multiplexed (``m2``)
    by no multiplexer signal (vw_pq.dbc's Motor_2 marks its multiplexer ``m``, not ``M``).

    Why: cantools leaves them out of the message's signal tree, and canical's generated codecs
    decoded them as plain signals, so the same frame decoded differently. Without them every
    codec canical builds has exactly cantools' signals."""
    kept = _tree_names(message.signal_tree)
    if len(kept) == len(message.signals):
        return
    dropped = [s.name for s in message.signals if s.name not in kept]
    message.signals[:] = [s for s in message.signals if s.name in kept]
    _UNDECODED[message.name] = tuple(dropped)


#: Per message name, the signals left out because no multiplexer signal selects them (to say why
#: a configuration naming one is refused).
_UNDECODED: dict[str, tuple[str, ...]] = {}


def undecoded_reason(message: str, signal: str) -> str | None:
    """Why ``signal`` of ``message`` is not there to use, when it was left out (None: it was not)."""
    if signal in _UNDECODED.get(message, ()):
        return (f"signal {signal} of {message} is multiplexed, but no signal of {message} is its "
                "multiplexer (M): cantools does not decode it, nor does canical")
    return None


def _layout(message: Message) -> tuple[object, ...]:
    """What makes two definitions of a message the same: id, length and every signal's encoding."""
    return (message.name, message.frame_id, message.is_extended_frame, message.length, message.is_fd,
            tuple((s.name, s.start, s.length, s.byte_order, s.is_signed, s.is_float, s.conversion.scale,
                   s.conversion.offset, s.minimum, s.maximum, s.is_multiplexer,
                   tuple(s.multiplexer_ids or ()), s.multiplexer_signal) for s in message.signals))


@dataclass(frozen=True)
class _Seen:
    message: Message
    path: Path


class _Merge:
    """Messages of several files by name and by id, each with the file that defined it."""

    def __init__(self) -> None:
        self.by_name: dict[str, _Seen] = {}
        self.by_id: dict[tuple[int, bool], _Seen] = {}

    def add(self, message: Message, path: Path, *, yield_to_user: bool = False) -> None:
        key = (message.frame_id, message.is_extended_frame)
        named, at_id = self.by_name.get(message.name), self.by_id.get(key)
        if yield_to_user and (named or at_id):
            return  # the user's own definition of a canical frame wins
        if named and _layout(named.message) != _layout(message):
            raise CanicalError(f"message {message.name} is defined differently in {named.path} and {path}")
        if at_id and at_id.message.name != message.name:
            ext = "extended " if key[1] else ""
            raise CanicalError(f"{ext}id {key[0]:#x} is {at_id.message.name} in {at_id.path} "
                               f"and {message.name} in {path}")
        if named:
            return  # the same message twice
        seen = _Seen(message, path)
        self.by_name[message.name] = seen
        self.by_id[key] = seen


def load_dbc(paths: DbcPaths, *, with_shipped: bool = True) -> Database:
    """Load one or several DBC files (and canical's own frames) as one database.

    Each bad file is one :class:`CanicalError` line; messages that load only non-strictly
    are named once on stderr (:func:`require_sound` refuses the ones canical uses).
    """
    files = dbc_list(paths)
    if not files:
        raise CanicalError("no DBC file given")
    merge, nodes = _Merge(), {}
    relaxed: list[str] = []
    for path in files:
        db = _load_one(path)
        for message in db.messages:
            merge.add(message, path)
            if why_broken(message) is not None:
                relaxed.append(message.name)
        nodes.update({n.name: n for n in db.nodes})
    shipped = shipped_dbc_path()
    if with_shipped and shipped.is_file() and all(p.resolve() != shipped.resolve() for p in files):
        for message in _load_one(shipped).messages:
            merge.add(message, shipped, yield_to_user=True)
    _warn_relaxed(files, relaxed)
    if isinstance(paths, DbcSet) and paths.j1939:
        mark_j1939(merge, paths.j1939, files)
    return Database(messages=[s.message for s in merge.by_name.values()], nodes=list(nodes.values()),
                    strict=False)


def mark_j1939(merge: _Merge, names: frozenset[str], files: tuple[Path, ...]) -> None:
    """Mark the named messages (or every extended one of the user's files) as J1939 parameter
    groups, as cantools marks those its attributes name; a name no file has is one error line."""
    user = set(files)
    if ALL_EXTENDED in names:
        chosen = [s.message for s in merge.by_name.values() if s.path in user and s.message.is_extended_frame]
    else:
        missing = sorted(n for n in names if n not in merge.by_name)
        if missing:
            raise CanicalError(f"j1939.messages: no message {', '.join(missing)} in {dbc_label(files)}")
        chosen = [merge.by_name[n].message for n in sorted(names)]
    for message in chosen:
        if not message.is_extended_frame:
            raise CanicalError(f"j1939.messages: {message.name} has a standard (11-bit) id; a J1939 "
                               "parameter group has a 29-bit one")
        message.protocol = "j1939"


def _warn_relaxed(files: tuple[Path, ...], relaxed: list[str]) -> None:
    """Name, once per process, the messages that cantools had to load non-strictly."""
    key = (dbc_label(files), tuple(sorted(set(relaxed))))
    if not relaxed or key in _WARNED:
        return
    _WARNED.add(key)
    names = ", ".join(sorted(set(relaxed)))
    print(f"canical: warning: {key[0]}: loaded non-strictly (overlapping or oversized signals, "
          f"not used unless named): {names}", file=sys.stderr)
