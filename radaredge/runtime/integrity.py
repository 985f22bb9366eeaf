"""Content hashes of exported graphs (``radaredge.content_sha256``): recomputed from the ``.onnx``
file itself, so a graph edited after export is named rather than trusted.

Standard library only: the ONNX file is read as protobuf wire format at the top level of its
``ModelProto`` (no ``onnx`` package, no onnxruntime).

What the hash covers (scheme 1): sha256 of, in this order,

1. ``radaredge.content_sha256/1\\n``;
2. the total length of the records of 3., as 8 bytes big-endian;
3. every top-level field record of the serialized ``ModelProto`` except ``doc_string`` (field 6)
   and ``metadata_props`` (field 14), byte for byte (tag, length and payload) in file order:
   the whole ``graph`` (every node and its attributes, every initializer, inputs, outputs,
   value_info, sparse initializers, subgraphs), ``ir_version``, ``opset_import``,
   ``producer_name``/``producer_version``, ``domain``, ``model_version``, ``functions``,
   ``training_info`` and any field a later ONNX adds;
4. the number of entries of 5., as 8 bytes big-endian;
5. every ``metadata_props`` entry whose key starts with ``radaredge.`` except
   ``radaredge.content_sha256`` itself, sorted by (key, value), each as 8-byte big-endian
   length + key bytes + 8-byte big-endian length + value bytes (UTF-8).

So every weight, node and radaredge metadata entry (card, weights hash, declared checks, input
error mask, ...) is covered, in an order that does not depend on where the metadata entries sit
in the file; the model's top-level ``doc_string`` (free text) and metadata entries of other tools
(keys not starting with ``radaredge.``) are not, so a tool that adds its own metadata leaves the
hash valid. radaredge writes no external-data files (every export is one self-contained
``.onnx``): moving a tensor out to an external file rewrites the ``graph`` record, so such a
graph no longer matches the hash recorded at export.

This is an integrity check, not a signature: it catches a graph edited after export, by hand or
by a tool (one initializer changed, a node rewired, metadata copied onto another graph), and a
file damaged on disk; whoever edits a graph on purpose can recompute the hash. It is computed
once per file identity (device, inode, size and modification time in ns) in a process, so
loading the same unchanged file again costs no hashing.
"""

from __future__ import annotations

import hashlib
import mmap
import os
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from .metadata import CONTENT_SHA256, PREFIX

SCHEME = b"radaredge.content_sha256/1\n"
_DOC_STRING, _METADATA_PROPS = 6, 14
_LEN = 2  # wire type of a length-delimited field
_KEY = CONTENT_SHA256.encode()
_PREFIX = PREFIX.encode()
CACHE_SIZE = 256  # file identities remembered per process
RACY_NS = 2_000_000_000  # a file modified this recently is not remembered (see content_hash)


class WireError(ValueError):
    """The bytes are not a well-formed protobuf message."""


def _varint(buf, pos: int, end: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= end or shift > 63:
            raise WireError(f"truncated or overlong varint at byte {pos}")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if b < 0x80:
            return value, pos
        shift += 7


def _records(buf, start: int, end: int):
    """(field number, wire type, record start, payload start, record end) of each field record of
    the message in ``buf[start:end]``."""
    pos = start
    while pos < end:
        begin = pos
        tag, pos = _varint(buf, pos, end)
        field, wire = tag >> 3, tag & 7
        if field == 0:
            raise WireError(f"field number 0 at byte {begin}")
        if wire == 0:
            _, pos = _varint(buf, pos, end)
            payload = pos
        elif wire == 1:
            payload, pos = pos, pos + 8
        elif wire == _LEN:
            n, payload = _varint(buf, pos, end)
            pos = payload + n
        elif wire == 5:
            payload, pos = pos, pos + 4
        else:  # groups (3, 4) are not used by ONNX; 6, 7 do not exist
            raise WireError(f"wire type {wire} at byte {begin}")
        if pos > end:
            raise WireError(f"field {field} at byte {begin} runs past the end")
        yield field, wire, begin, payload, pos


def _entry(buf, start: int, end: int) -> tuple[bytes, bytes]:
    """(key, value) of a ``StringStringEntryProto``."""
    key = value = b""
    for field, wire, _, payload, stop in _records(buf, start, end):
        if wire == _LEN and field == 1:
            key = bytes(buf[payload:stop])
        elif wire == _LEN and field == 2:
            value = bytes(buf[payload:stop])
    return key, value


@dataclass(frozen=True)
class ContentHash:
    """A graph file's content hash: ``computed`` from its bytes now, and the ``recorded`` value of
    its ``radaredge.content_sha256`` entry (None when it has none); ``recorded_times`` how many
    such entries the file holds."""

    computed: str
    recorded: str | None
    recorded_times: int = 1

    @property
    def status(self) -> str:
        """``verified``, ``mismatch`` or ``not recorded``."""
        if self.recorded is None:
            return "not recorded"
        return "verified" if self.recorded_times == 1 and self.recorded == self.computed else "mismatch"


def content_hash_of(data) -> ContentHash:
    """The :class:`ContentHash` of the serialized ``ModelProto`` ``data`` (bytes, memoryview or
    mmap); WireError when it is not well-formed protobuf."""
    n = len(data)
    spans, entries, recorded = [], [], []
    for field, wire, begin, payload, stop in _records(data, 0, n):
        if field == _DOC_STRING:
            continue
        if field == _METADATA_PROPS and wire == _LEN:
            key, value = _entry(data, payload, stop)
            if key == _KEY:
                recorded.append(value.decode("utf-8", "replace"))
            elif key.startswith(_PREFIX):
                entries.append((key, value))
            continue
        spans.append((begin, stop))
    h = hashlib.sha256(SCHEME)
    h.update(sum(stop - begin for begin, stop in spans).to_bytes(8, "big"))
    view = memoryview(data)
    try:
        for begin, stop in spans:
            h.update(view[begin:stop])
    finally:
        view.release()
    h.update(len(entries).to_bytes(8, "big"))
    for key, value in sorted(entries):
        h.update(len(key).to_bytes(8, "big") + key + len(value).to_bytes(8, "big") + value)
    return ContentHash(h.hexdigest(), recorded[0] if recorded else None, len(recorded))


_cache: OrderedDict[tuple, ContentHash] = OrderedDict()
_lock = threading.Lock()
_stats = {"computed": 0, "cached": 0}


def _identity(st: os.stat_result) -> tuple:
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def content_hash(path: str | Path) -> ContentHash:
    """The :class:`ContentHash` of the graph file at ``path``, remembered per file identity
    (st_dev, st_ino, st_size, st_mtime_ns) in this process: an unchanged file is hashed once.
    A file modified less than :data:`RACY_NS` before it is hashed, or while it is read, is not
    remembered (as git's racy-file rule: an edit of the same size within the file system's
    timestamp granularity would keep the identity), so it is hashed again at its next load.
    InputError when the file cannot be read or is not well-formed protobuf."""
    try:
        with open(path, "rb") as f:
            key = _identity(os.fstat(f.fileno()))
            with _lock:
                found = _cache.get(key)
                if found is not None:
                    _cache.move_to_end(key)
                    _stats["cached"] += 1
                    return found
            if key[2] == 0:
                raise WireError("the file is empty")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                result = content_hash_of(data)
            unchanged = _identity(os.fstat(f.fileno())) == key and time.time_ns() - key[3] >= RACY_NS
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except WireError as exc:
        raise InputError(
            f"{path}: not a well-formed ONNX file ({exc}); pass an .onnx written by `radaredge export`"
        ) from None
    with _lock:
        _stats["computed"] += 1
        if unchanged:
            _cache[key] = result
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
    return result


def cache_stats() -> dict[str, int]:
    """How many content hashes this process ``computed`` and how many it found ``cached``."""
    with _lock:
        return dict(_stats, entries=len(_cache))


def clear_cache() -> None:
    """Forget every remembered content hash (the counts of :func:`cache_stats` too)."""
    with _lock:
        _cache.clear()
        _stats.update(computed=0, cached=0)


MISMATCH = "its contents do not match the hash recorded at export: the graph was edited after export; re-export it"
NOT_RECORDED = (
    "exported before radaredge recorded content hashes (no radaredge.content_sha256 in its metadata), "
    "so an edit made after export cannot be detected; re-export it to have its contents checked"
)


def finding(found: ContentHash) -> str | None:
    """What is wrong with ``found`` (None unless it is a mismatch), with both hashes."""
    if found.status != "mismatch":
        return None
    if found.recorded_times > 1:
        return f"{MISMATCH} (radaredge.content_sha256 is given {found.recorded_times} times)"
    return f"{MISMATCH} (recorded {found.recorded}, its contents hash to {found.computed})"


def describe(found: ContentHash) -> str:
    """One line on ``found`` for ``radaredge inspect``: ``verified (<hash>)``, ``not recorded:
    ...`` or ``MISMATCH: ...``."""
    if found.status == "verified":
        return f"verified ({found.computed})"
    if found.status == "not recorded":
        return f"not recorded: {NOT_RECORDED}"
    return f"MISMATCH: {finding(found)}"


def check_content(path: str | Path) -> ContentHash:
    """:func:`content_hash` of ``path``, checked: InputError (``<path>: its contents do not match
    ...``) when it differs from the hash recorded at export; a RuntimeWarning when the graph
    records none (an export from before content hashes: accepted, as it always was)."""
    found = content_hash(path)
    if found.status == "mismatch":
        raise InputError(f"{path}: {MISMATCH}")
    if found.status == "not recorded":
        warnings.warn(f"{path}: {NOT_RECORDED}", RuntimeWarning, stacklevel=3)
    return found
