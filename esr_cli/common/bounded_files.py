"""Reading a file esr did not necessarily write (a store's, an archive's, a study's) with bounded
work. A file is opened without blocking and without following a link, and read only once the
open file is known to be a regular one: a FIFO or a device put in a file's place is refused, never
waited on or read without end (nor is a name checked first and opened after, when something else
may lie there). Reads stop one byte past their limit, so a size the system misreports (/proc)
cannot make esr read more."""

from __future__ import annotations

import errno
import fcntl
import io
import os
import stat
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np


class UnreadableInput(ValueError):
    """A file esr refuses to read; `str()` is one line."""


def open_regular(path: Path, follow_links: bool = False) -> BinaryIO:
    """`path` open for reading, once the open file is known to be a regular one. Opened without
    blocking (a FIFO does not wait for a writer) and, unless `follow_links`, without following a
    link, then made blocking again. OSError where it cannot be opened (FileNotFoundError where
    nothing is there); UnreadableInput where it is a link or not a regular file."""
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow_links else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except OSError as e:
        if e.errno == errno.ELOOP and not follow_links:  # O_NOFOLLOW met a link
            raise UnreadableInput("a link, not a regular file") from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO would block the reader, a device never end
            raise UnreadableInput("not a regular file")
        mode = fcntl.fcntl(fd, fcntl.F_GETFL)
        if mode & os.O_NONBLOCK:
            fcntl.fcntl(fd, fcntl.F_SETFL, mode & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def size_problem(f: BinaryIO, max_bytes: int) -> UnreadableInput | None:
    """The refusal of an open file larger than `max_bytes`, or None."""
    size = os.fstat(f.fileno()).st_size
    return UnreadableInput(f"{size:,} bytes, more than the {max_bytes:,} esr reads") if size > max_bytes else None


def read_at_most(f: BinaryIO, max_bytes: int) -> bytes:
    """All of the open file `f`; UnreadableInput where it holds more than `max_bytes`."""
    too_large = size_problem(f, max_bytes)
    if too_large:
        raise too_large
    data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise UnreadableInput(f"more than the {max_bytes:,} bytes esr reads")
    return data


def read_bytes(path: Path, max_bytes: int, follow_links: bool = False) -> bytes:
    """The bytes of the regular file `path` (see open_regular); UnreadableInput where it is a
    link, not a regular file or larger than `max_bytes`; OSError where it cannot be read."""
    with open_regular(path, follow_links) as f:
        return read_at_most(f, max_bytes)


def copy_file(src: Path, dst: Path, max_bytes: int) -> None:
    """Copy the regular file `src` (never a link, see open_regular) of at most `max_bytes` to a new
    file `dst`; UnreadableInput where `src` is refused."""
    data = read_bytes(src, max_bytes)
    with open(dst, "xb") as f:
        f.write(data)


def load_npz(path: Path, max_bytes: int) -> dict[str, np.ndarray]:
    """The arrays of the .npz file `path`, with both its size on disk and the arrays it unpacks to
    at most `max_bytes` (a compressed member may unpack to far more than it holds). No pickled
    objects are read. UnreadableInput where the file is refused or is not an .npz of plain arrays."""
    data = read_bytes(path, max_bytes)
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            unpacked = sum(info.file_size for info in z.infolist())
            if unpacked > max_bytes:
                raise UnreadableInput(f"unpacks to {unpacked:,} bytes, more than the {max_bytes:,} esr reads")
            for info in z.infolist():
                _check_array_header(z, info)
        with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
            return {name: arrays[name] for name in arrays.files}
    except UnreadableInput:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, KeyError, EOFError) as e:
        raise UnreadableInput(f"not an .npz file of plain arrays ({str(e)[:80]})") from None


def _check_array_header(z: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """Refuse a member whose .npy header declares an array larger than the member holds: numpy
    allocates the declared array before it reads a byte of it."""
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with z.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version not in readers:
            raise UnreadableInput(f"{info.filename[:60]!r} is an .npy of format {version}, which esr does not write")
        shape, _, dtype = readers[version](member)
    if dtype.hasobject:
        raise UnreadableInput(f"{info.filename[:60]!r} holds Python objects, not a plain array")
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if declared > info.file_size:
        raise UnreadableInput(f"{info.filename[:60]!r} declares {declared:,} bytes of array in a member of {info.file_size:,}")
