"""Atomic file writes: a killed process never leaves a half-written file behind.

Every writer goes to a temporary file in the destination folder, flushes it to disk and
renames it over the destination (``os.replace`` is atomic on POSIX and Windows).

Output names made from data (track ids, log, sequence and camera names read from files) go
through :func:`safe_stem`, and the path through :func:`contained_path`, so that a name like
``../x`` or ``/etc/passwd`` stored in a file cannot write outside the output folder.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
import tempfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from seqshape.errors import DataError
from seqshape.limits import MAX_FILE_BYTES

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; use the usual default
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            # a full disk's error names no file: name the one being written
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as fh:
        fh.write(text)


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def atomic_save_npz(path: str | Path, compressed: bool = True, **arrays: np.ndarray) -> None:
    with atomic_open(path, "wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def check_regular(path: str | Path, what: str, kind: str = "text") -> int:
    """The size of ``path`` after checking, without opening it, that it is a regular file
    (symbolic links followed) of at most ``MAX_FILE_BYTES[kind]`` bytes.

    A FIFO, a device, a socket or a folder where a file belongs is refused at once (opening a
    FIFO would block until a writer comes); every refusal is a :class:`DataError` naming the
    path and the kind of file (``what``).
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DataError(path, f"{what} not found") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the name
        raise DataError(path, f"unreadable {what} ({_words(exc)})") from None
    if not stat.S_ISREG(st.st_mode):
        raise DataError(path, f"{what} is {_file_type(st.st_mode)}, not a regular file; "
                              "refusing to read it")
    limit = MAX_FILE_BYTES[kind]
    if st.st_size > limit:
        raise DataError(path, f"{what} of {st.st_size} bytes is larger than any real one "
                              f"(limit {limit} bytes); refusing to read it")
    return st.st_size


@contextlib.contextmanager
def open_regular(path: str | Path, what: str, kind: str = "text") -> Iterator[IO[bytes]]:
    """Open ``path`` for reading bytes after :func:`check_regular`; the file is opened without
    blocking and checked again on its descriptor, so a FIFO swapped in between cannot hang.
    Errors while opening are :class:`DataError` naming the path."""
    check_regular(path, what, kind)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise DataError(path, f"unreadable {what} ({_words(exc)})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise DataError(path, f"{what} is {_file_type(mode)}, not a regular file; "
                                  "refusing to read it")
        fh = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with fh:
        yield fh


def read_bytes(path: str | Path, what: str, kind: str = "text") -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`, bounded by
    ``MAX_FILE_BYTES[kind]``); a read error is a :class:`DataError` naming it."""
    limit = MAX_FILE_BYTES[kind]
    with open_regular(path, what, kind) as fh:
        try:
            size = os.fstat(fh.fileno()).st_size
            data = fh.read(size + 1)  # one byte more: a file that grew is read on, bounded
            if len(data) > size:
                chunks, total = [data], len(data)
                while chunk := fh.read(1 << 20):
                    total += len(chunk)
                    if total > limit:
                        raise DataError(path, f"{what} is larger than {limit} bytes")
                    chunks.append(chunk)
                data = b"".join(chunks)
        except OSError as exc:
            raise DataError(path, f"unreadable {what} ({_words(exc)})") from None
    return data


def read_text(path: str | Path, what: str, encoding: str = "utf-8") -> str:
    """The text of ``path``; a missing, unreadable, non-regular or over-long file, bytes that
    are not ``encoding``, or a NUL character is a DataError naming it (and the NUL's line).

    ``what`` names the kind of file in the message ("label file", "calibration file", ...).
    """
    data = read_bytes(path, what, "text")
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise DataError(path, f"unreadable {what} ({exc})") from None
    if "\0" in text:
        line = len((text[:text.index("\0")] + "x").splitlines())  # as splitlines numbers
        raise DataError(path, f"NUL character in a {what} (a binary file, or a corrupt "
                              "one)", line=line)
    if "\r" in text:  # universal newlines, as Path.read_text gives
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    return text


def _words(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


def _file_type(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


MAX_STEM = 120  #: longest name :func:`safe_stem` returns
_UNSAFE_CHARS = re.compile(r"[^A-Za-z0-9._-]")


def safe_stem(name: object, max_length: int = MAX_STEM) -> str:
    """A file-name stem made from ``name`` (a track id, a log name...) that stays in its folder.

    ASCII letters, digits and ``-_.`` are kept, every other character (``/``, ``\\``, spaces,
    non-ASCII letters, control characters) becomes ``_``; leading dots are dropped (no ``..``,
    no hidden files); an empty result is ``_``. A stem longer than ``max_length`` (at least 16)
    is cut and ends in ``-`` plus 8 hex digits of the CRC-32 of the whole name, so long names
    that differ only at the end stay apart. Deterministic (the same name gives the same stem
    on every run and machine). Different names can give the same stem (``a/b`` and ``a_b``).

    >>> safe_stem("../escaped"), safe_stem("/etc/passwd"), safe_stem(""), safe_stem("..")
    ('_escaped', '_etc_passwd', '_', '_')
    >>> safe_stem("Straße 7")
    'Stra_e_7'
    """
    if max_length < 16:
        raise ValueError(f"max_length must be at least 16, got {max_length}")
    text = str(name)
    stem = _UNSAFE_CHARS.sub("_", text).lstrip(".") or "_"
    if len(stem) > max_length:
        digest = zlib.crc32(text.encode("utf-8", "surrogatepass")) & 0xFFFFFFFF
        stem = f"{stem[:max_length - 9]}-{digest:08x}"
    return stem


def contained_path(folder: str | Path, name: str | Path, *, source: str | Path | None = None,
                   what: str = "output name", folder_kind: str = "folder") -> Path:
    """``folder / name``, checked to resolve inside ``folder`` (symbolic links followed).

    The one containment check for names that come from data: output names (already made safe
    by :func:`safe_stem`; this is the last check before a write) and paths read from a file
    (a manifest's track files). A path that leaves ``folder`` (``..``, an absolute name, a
    link pointing out) is a :class:`~seqshape.errors.DataError` naming ``source`` (the file
    the name came from) or else the path itself; ``what`` and ``folder_kind`` word the message.
    """
    folder = Path(folder)
    path = folder / name
    root = folder.resolve()
    target = path.resolve()
    if target == root or not target.is_relative_to(root):
        raise DataError(source if source is not None else path,
                        f"{what} {str(name)!r} resolves to {target}, outside the {folder_kind} "
                        f"{root}; refusing to follow it")
    return path
