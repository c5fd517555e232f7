"""Signed archives: `esr export --sign` and `esr import --require-signature` (docs/store.md).

An archive's digests find damage, not a forger, who can recompute them (docs/reliability.md,
"Threat model"). A signature can: an HMAC-SHA256 of the archive's bytes under a secret key that
only those who export and import hold, in a file that $ESR_ARCHIVE_KEY names. It is written
beside the archive as ARCHIVE.sig; with --require-signature an archive without one, or whose
bytes it does not match, is refused before anything else is read from it.
"""

from __future__ import annotations

import hashlib
import hmac
import os
from pathlib import Path

from esr_cli.common import bounded_files, tar_reader
from esr_cli.storage.store import StoreError, atomic_write_text

KEY_ENV = "ESR_ARCHIVE_KEY"
MIN_KEY_BYTES, MAX_KEY_BYTES = 32, 4096
SIG_SUFFIX, SIG_TAG = ".sig", "esr-archive-hmac-sha256"


def archive_key() -> bytes:
    """The key in the file $ESR_ARCHIVE_KEY names; StoreError where it is unset or unfit."""
    where = os.environ.get(KEY_ENV, "")
    if not where.strip():
        raise StoreError(f"${KEY_ENV} is not set: name a file holding the archive key, {MIN_KEY_BYTES} random bytes or "
                         f"more, that only those who export and import can read (`head -c 32 /dev/urandom > KEYFILE`)")
    key = _read_small(Path(where), MAX_KEY_BYTES, f"${KEY_ENV}={where}")
    if len(key) < MIN_KEY_BYTES:
        raise StoreError(f"${KEY_ENV}={where}: {len(key)} bytes; an archive key has at least {MIN_KEY_BYTES}")
    return key


def signature_path(archive: Path) -> Path:
    return Path(archive).with_name(Path(archive).name + SIG_SUFFIX)


def sign(archive: Path, key: bytes) -> Path:
    """Write ARCHIVE.sig for `archive`; -> its path."""
    path = signature_path(archive)
    atomic_write_text(path, f"{SIG_TAG} {_mac(Path(archive), key)}\n")
    return path


def check_signature(archive: Path, key: bytes) -> None:
    """Raise StoreError unless ARCHIVE.sig holds the archive's HMAC under `key`."""
    path = signature_path(archive)
    if not os.path.lexists(path):
        raise StoreError(f"{archive} has no signature ({path.name} beside it): --require-signature refuses it")
    text = _read_small(path, 4 * len(SIG_TAG) + 128, str(path)).decode(errors="replace").strip()
    tag, _, want = text.partition(" ")
    if tag != SIG_TAG or not hmac.compare_digest(want, _mac(Path(archive), key)):
        raise StoreError(f"{archive} does not match its signature {path.name}: it was changed after it was signed, "
                         f"or signed with another key; nothing imported")


def _mac(archive: Path, key: bytes) -> str:
    mac = hmac.new(key, digestmod=hashlib.sha256)
    try:
        with tar_reader.open_archive(archive) as f:  # a regular gzip file within the size limit
            for block in iter(lambda: f.read(1 << 20), b""):
                mac.update(block)
    except tar_reader.ArchiveError as e:
        raise StoreError(f"{archive}: {e}") from None
    return mac.hexdigest()


def _read_small(path: Path, limit: int, what: str) -> bytes:
    """A regular file of at most `limit` bytes (bounded_files.read_bytes: a FIFO is refused)."""
    try:
        return bounded_files.read_bytes(path, limit, follow_links=True)
    except bounded_files.UnreadableInput as e:
        raise StoreError(f"{what}: {e}") from None
    except OSError as e:
        raise StoreError(f"{what}: cannot be read ({e.strerror or e})") from None
