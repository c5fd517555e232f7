"""Reading the archive `esr import` is given (esr_cli/storage/transfer.py), with every bound checked on
the raw stream before the bytes it guards are read (docs/reliability.md, "Archives").

Python's tarfile is not used on an archive: it reads an extended header's whole body into memory
whatever size the header claims, follows a chain of them by recursion, takes any compression it
recognises, and ends an archive silently at a damaged header. This reader takes only what
`esr export` writes, a gzip-compressed POSIX tar of plain files and folders, and reads it as a
stream: the gzip stream is inflated a chunk at a time, each 512-byte header is checked (checksum,
size, type, name) before its body is read, an extended header's body (a pax record list or a GNU
long name) only up to MAX_HEADER_BYTES, and the declared sizes are summed before any data is
read. A second pass unpacks (`unpack`) once a first (`members`) has checked everything, so
nothing is written for an archive that fails a check.
"""

from __future__ import annotations

import os
import re
import stat
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Iterator

# Far above any real artifact (a run is a few dozen files of at most tens of MiB, its deepest
# path 9 levels and 134 bytes), low enough that a hostile archive can fill neither a disk nor
# memory, nor an inode table.
MAX_ARCHIVE_BYTES = 4 << 30  # the archive file, compressed
MAX_UNPACKED_BYTES = 4 << 30  # the sizes of all its files together
MAX_MEMBERS = 10_000  # files and folders
MAX_DEPTH = 32  # folders in a member's path, the artifact's own three included
MAX_NAME_BYTES = 1024  # a member's whole path; each part at most NAME_MAX_BYTES, as file systems allow
NAME_MAX_BYTES = 255
MAX_HEADER_BYTES = 64 << 10  # the body of one pax or GNU long-name header; esr's are under 1 KiB
MAX_PADDING_BYTES = 64 << 10  # zeros after the end-of-archive block (tar pads to its record size)

SUFFIXES = (".tar.gz", ".tgz")
BLOCK = 512
CHUNK = 1 << 20  # compressed bytes read, and inflated bytes made, at a time
GZIP_WBITS = 16 + zlib.MAX_WBITS  # a gzip wrapper: its header and its CRC-32 and length are checked
FILE_TYPES, DIR_TYPE, EXTENDED_TYPES = (b"0", b"\0", b"7"), b"5", (b"x", b"L", b"K")
# What other compressors and a bare tar start with: named, so a mismatch says what the file is.
MAGIC = ((b"\x1f\x8b", "gzip"), (b"BZh", "bzip2"), (b"\xfd7zXZ\0", "xz"), (b"\x28\xb5\x2f\xfd", "zstd"),
         (b"\x04\x22\x4d\x18", "lz4"))


class ArchiveError(Exception):
    """An archive esr does not read; `str()` is one line, without the archive's name."""


@dataclass(frozen=True)
class Member:
    name: str  # as the header gives it, a folder's without its trailing slash
    is_dir: bool
    size: int  # 0 for a folder


def open_archive(path: Path) -> BinaryIO:
    """The archive file, open for reading, once it is known to be a regular file of at most
    MAX_ARCHIVE_BYTES, named .tar.gz or .tgz and gzip-compressed. Never blocks: a FIFO is opened
    without waiting for a writer, and refused."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise ArchiveError("no archive by that name") from None
    except OSError as e:
        raise ArchiveError(f"cannot be opened ({e.strerror or e})") from None
    try:
        _check_file(fd, path.name)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb")


def _check_file(fd: int, name: str) -> None:
    st = os.fstat(fd)
    if stat.S_ISDIR(st.st_mode):
        raise ArchiveError("a directory, not an archive (`esr export` writes a .tar.gz file)")
    if not stat.S_ISREG(st.st_mode):  # a FIFO would wait for a writer, a device never end
        raise ArchiveError("not a regular file (a pipe or a device is never read)")
    if st.st_size > MAX_ARCHIVE_BYTES:
        raise ArchiveError(f"{st.st_size:,} bytes, more than the {MAX_ARCHIVE_BYTES:,} esr imports: not an esr artifact")
    if not name.endswith(SUFFIXES):
        raise ArchiveError("not named .tar.gz or .tgz: esr imports the gzip-compressed tar archives `esr export` writes")
    head = os.pread(fd, BLOCK + 8, 0)
    found = next((what for magic, what in MAGIC if head.startswith(magic)), None)
    if found is None and head[257:262] == b"ustar":
        found = "an uncompressed tar"
    if found is None:
        raise ArchiveError("not a tar archive, or a damaged one (`esr export` writes gzip-compressed tar archives)")
    if found != "gzip":
        what = found if found.startswith("an ") else f"{found}-compressed"
        raise ArchiveError(f"{what}, though its name says gzip: esr imports the gzip-compressed tar archives "
                           "`esr export` writes")


class _Inflated:
    """The archive's bytes inflated, a chunk at a time (never more than CHUNK in memory), its
    compressed size counted as it is read (the file may grow after it was measured)."""

    def __init__(self, f: BinaryIO):
        self.f, self.read_bytes = f, 0
        self.d = zlib.decompressobj(GZIP_WBITS)
        self.chunk, self.pos = b"", 0

    def read(self, n: int) -> bytes:
        """At most n bytes: fewer only where the stream ends."""
        parts = []
        while n > 0:
            if self.pos == len(self.chunk):
                self.chunk, self.pos = self._inflate(), 0
                if not self.chunk:
                    break
            part = self.chunk[self.pos:self.pos + n]
            self.pos += len(part)
            n -= len(part)
            parts.append(part)
        return b"".join(parts)

    def exactly(self, n: int) -> bytes:
        data = self.read(n)
        if len(data) < n:
            raise ArchiveError("cut short: the archive ends inside a member")
        return data

    def _compressed(self) -> bytes:
        data = self.f.read(CHUNK)
        self.read_bytes += len(data)
        if self.read_bytes > MAX_ARCHIVE_BYTES:
            raise ArchiveError(f"more than the {MAX_ARCHIVE_BYTES:,} bytes esr imports")
        return data

    def _inflate(self) -> bytes:
        """The next inflated bytes; b"" where the last gzip member and the file end together."""
        try:
            while True:
                if self.d.eof:  # a gzip member ended: another may follow
                    data = self.d.unused_data or self._compressed()
                    if not data:
                        return b""
                    self.d = zlib.decompressobj(GZIP_WBITS)
                else:
                    data = self.d.unconsumed_tail or self._compressed()
                out = self.d.decompress(data, CHUNK)
                if out:
                    return out
                if not data and not self.d.eof:
                    raise ArchiveError("cut short: the gzip stream ends early")
        except zlib.error as e:
            raise ArchiveError(f"damaged gzip data ({e})") from None


def members(f: BinaryIO) -> Iterator[Member]:
    """Every member of the archive open in `f`, from its start, each checked against the bounds
    before its body is read; the whole archive is read to its end (the gzip checksum included)."""
    yield from _Reader(f).members()


def unpack(f: BinaryIO, dest: Path, expected: list[Member]) -> None:
    """Write the archive's members under `dest`. They must be `expected`, what `members` read
    before: an archive changed in between is refused, not trusted. Only plain files and folders
    are made, each file new (none is opened through a link, none is written twice)."""
    reader = _Reader(f)
    got = 0
    for i, m in enumerate(reader.members()):
        if i >= len(expected) or m != expected[i]:
            raise ArchiveError("the archive changed while it was read")
        inside = PurePosixPath(m.name)
        if inside.is_absolute() or ".." in inside.parts:  # `members` takes any name; the caller checks them
            raise ArchiveError(f"member {m.name[:60]!r} points outside the artifact")
        target = dest.joinpath(*inside.parts)
        if m.is_dir:
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            with os.fdopen(fd, "wb") as out:
                reader.copy_data(out)
        got += 1
    if got != len(expected):
        raise ArchiveError("the archive changed while it was read")


_OCTAL = re.compile(rb"[0-7]*")
_PAX_LENGTH = re.compile(rb"([0-9]{1,20}) ")


class _Reader:
    def __init__(self, f: BinaryIO):
        f.seek(0)
        self.stream = _Inflated(f)
        self.left = 0  # the current member's data not yet read
        self.padding = 0  # and the zeros after it, to the next block

    def members(self) -> Iterator[Member]:
        count = total = 0
        while True:
            self._skip_data()
            block = self.stream.exactly(BLOCK)
            if block == bytes(BLOCK):
                self._check_end()
                return
            member = self._member(block)
            count += 1
            if count > MAX_MEMBERS:
                raise ArchiveError(f"more than {MAX_MEMBERS:,} members: not an esr artifact")
            total += member.size
            if total > MAX_UNPACKED_BYTES:
                raise ArchiveError(f"unpacks to more than {MAX_UNPACKED_BYTES:,} bytes: not an esr artifact")
            self.left, self.padding = member.size, -member.size % BLOCK
            yield member

    def copy_data(self, out: BinaryIO) -> None:
        while self.left:
            data = self.stream.exactly(min(self.left, CHUNK))
            out.write(data)
            self.left -= len(data)

    def _skip_data(self) -> None:
        while self.left:
            self.left -= len(self.stream.exactly(min(self.left, CHUNK)))
        self.stream.exactly(self.padding)
        self.padding = 0

    def _member(self, block: bytes) -> Member:
        """The member whose header is `block`, after the extended headers before it (at most one
        of each kind, each body at most MAX_HEADER_BYTES)."""
        extended: dict[bytes, bytes] = {}
        seen: set[bytes] = set()
        while True:
            kind, size, name = _header(block)
            if kind not in EXTENDED_TYPES:
                break
            if kind in seen:
                raise ArchiveError("two extended headers of one kind before a member: not an esr artifact")
            if size > MAX_HEADER_BYTES:
                raise ArchiveError(f"an extended header of {size:,} bytes, more than the {MAX_HEADER_BYTES:,} esr reads")
            seen.add(kind)
            body = self.stream.exactly(size + -size % BLOCK)[:size]
            if kind == b"x":
                extended.update(_pax_records(body))
            elif kind == b"L":
                extended[b"path"] = body.split(b"\0", 1)[0]
            block = self.stream.exactly(BLOCK)
        name = extended.get(b"path", name)
        if b"size" in extended:
            if not extended[b"size"].isdigit() or len(extended[b"size"]) > 20:
                raise ArchiveError("a damaged pax header (its size is not a number)")
            size = int(extended[b"size"])
        text = _name(name)
        if kind == DIR_TYPE and size == 0:
            return Member(text.rstrip("/"), True, 0)
        if kind in FILE_TYPES and not text.endswith("/"):
            return Member(text, False, size)
        raise ArchiveError(f"member {text!r} is not a plain file or folder (links and devices are refused)")

    def _check_end(self) -> None:
        """After the end-of-archive block: at most MAX_PADDING_BYTES of zeros, then the end of the
        gzip stream (read, so its checksum is checked) and of the file."""
        padding = self.stream.read(MAX_PADDING_BYTES + 1)
        if len(padding) > MAX_PADDING_BYTES or padding.count(0) != len(padding):
            raise ArchiveError("data after the end of the tar archive: not an esr artifact")


def _header(block: bytes) -> tuple[bytes, int, bytes]:
    """(type flag, size, name) of a 512-byte tar header, once its checksum is right."""
    stored = block[148:156].split(b"\0", 1)[0].strip()
    unsigned = sum(block[:148]) + 8 * 32 + sum(block[156:])
    signed = unsigned - 256 * sum(b >= 128 for b in block[:148] + block[156:])
    if not _OCTAL.fullmatch(stored) or not stored or int(stored, 8) not in (unsigned, signed):
        raise ArchiveError("a damaged tar header (its checksum does not match): not an archive esr wrote")
    name = block[:100].split(b"\0", 1)[0]
    prefix = block[345:500].split(b"\0", 1)[0]
    if block[257:263] == b"ustar\0" and prefix:  # POSIX ustar: a long name split in two
        name = prefix + b"/" + name
    return block[156:157], _size(block[124:136]), name


def _size(field: bytes) -> int:
    if field[0] == 0x80:  # base-256, as GNU tar writes a size past 8 GiB
        return int.from_bytes(field[1:], "big")
    digits = field.split(b"\0", 1)[0].strip()
    if field[0] & 0x80 or not _OCTAL.fullmatch(digits):
        raise ArchiveError("a damaged tar header (its size is not a number)")
    return int(digits or b"0", 8)


def _pax_records(body: bytes) -> dict[bytes, bytes]:
    """The `LENGTH key=value\\n` records of a pax header, each read to its stated length."""
    records, pos = {}, 0
    while pos < len(body):
        m = _PAX_LENGTH.match(body, pos)
        length = int(m.group(1)) if m else 0
        record = body[pos:pos + length]
        key, eq, value = record[len(m.group(0)) if m else 0:-1].partition(b"=")
        if not m or len(record) != length or not record.endswith(b"\n") or not eq or not key:
            raise ArchiveError("a damaged pax header: not an archive esr wrote")
        if key.startswith(b"GNU.sparse"):  # its data is laid out otherwise: esr never writes one
            raise ArchiveError("a sparse file: not an esr artifact")
        records[key] = value
        pos += length
    return records


def _name(raw: bytes) -> str:
    """A member's name, once it is UTF-8 text of bounded length and depth without a NUL."""
    try:
        text = raw.decode()
    except UnicodeDecodeError:
        raise ArchiveError(f"a member name that is not UTF-8 ({raw[:60]!r})") from None
    shown = repr(text[:60]) + ("..." if len(text) > 60 else "")
    if not text or "\0" in text:
        raise ArchiveError(f"a member with an empty name or a NUL in it ({shown})")
    if len(raw) > MAX_NAME_BYTES:
        raise ArchiveError(f"member {shown} has a name of {len(raw):,} bytes; at most {MAX_NAME_BYTES:,}")
    parts = text.rstrip("/").split("/")
    if len(parts) > MAX_DEPTH:
        raise ArchiveError(f"member {shown} lies {len(parts)} folders deep; at most {MAX_DEPTH}")
    if any(len(p.encode()) > NAME_MAX_BYTES for p in parts):
        raise ArchiveError(f"member {shown} has a part longer than {NAME_MAX_BYTES} bytes")
    return text
