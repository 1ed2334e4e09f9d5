"""Folders and files of a cache that only this user can change (the compilation cache,
diffshade.io.compile_cache): what is read from them is run, so they are held to the rules
ssh holds ~/.ssh to.

- `private_folder(path)` creates what is missing of `path` with mode 0700 and checks it;
- `check_folder(path)` refuses a folder that is not this user's (or root's), or that
  group or others can write;
- `read_private(path, limit)` reads an entry, refusing one that is not a plain file of
  this user's that only they can write, and one over `limit` bytes, before reading it;
- `write_private(path, data)` writes an entry atomically, mode 0600.

A refusal is an `Untrusted` error whose message names the path and what is wrong with it;
the caller warns (`warn_once`) and goes on without the cache. An entry over the limit is
a ValueError: a damaged entry, which the caller removes.
"""

import contextlib
import os
import stat
import sys
import tempfile

__all__ = ["MAX_ENTRY_BYTES", "Untrusted", "check_folder", "private_folder", "read_private",
           "warn_once", "write_private"]

FOLDER_MODE = 0o700
# far above any compiled program of diffshade's (a few MB at most): an entry beyond it is
# damage, refused before it is read
MAX_ENTRY_BYTES = 256 * 2**20
_LOOSE = stat.S_IWGRP | stat.S_IWOTH


class Untrusted(Exception):
    """A cache folder or entry that another user could have written."""


_warned = set()


def warn_once(text):
    """'diffshade: warning: text' on stderr, once per process."""
    if text not in _warned:
        _warned.add(text)
        print(f"diffshade: warning: {text}", file=sys.stderr)


def _owner():
    """The user whose cache it is (a function, so that tests can stand in for another)."""
    return os.geteuid()


def _owned(info):
    """Ours, or root's (who can change anything anyway)."""
    return info.st_uid in (_owner(), 0)


def _check(path, info, kind):
    """Refuse what is not ours or is writable by group or others."""
    if not _owned(info):
        raise Untrusted(f"{kind} {path!r} belongs to user id {info.st_uid}, not to this user "
                        f"({_owner()})")
    if info.st_mode & _LOOSE:
        raise Untrusted(f"{kind} {path!r} is writable by group or others (mode "
                        f"{stat.S_IMODE(info.st_mode):04o}; expected at most 0755, "
                        "e.g. chmod go-w)")


def check_folder(path):
    """Raise Untrusted unless `path` is a folder of this user's that only they can write."""
    info = os.stat(path)
    if not stat.S_ISDIR(info.st_mode):
        raise Untrusted(f"cache folder {path!r} is not a folder")
    _check(path, info, "cache folder")


def private_folder(path):
    """Create the missing folders of `path` (mode 0700), then check_folder(path)."""
    missing = []
    head = os.path.abspath(path)
    while not os.path.exists(head):
        missing.append(head)
        head = os.path.dirname(head)
    for folder in reversed(missing):
        with contextlib.suppress(FileExistsError):  # another process made it meanwhile
            os.mkdir(folder, FOLDER_MODE)
    check_folder(path)


def read_private(path, limit):
    """The bytes of the entry at `path`, or None when there is none. Raises Untrusted for
    an entry that is not a plain file of this user's or is writable by group or others,
    ValueError for one over `limit` bytes (both checked on the open file, before
    reading)."""
    try:
        handle = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return None
    except OSError as err:  # a link (ELOOP), or unreadable
        raise Untrusted(f"cache entry {path!r}: {err.strerror}") from None
    with os.fdopen(handle, "rb") as file:
        info = os.fstat(file.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise Untrusted(f"cache entry {path!r} is not a plain file")
        _check(path, info, "cache entry")
        if info.st_size > limit:
            raise ValueError(f"cache entry {path!r} holds {info.st_size} bytes; expected "
                             f"at most {limit}")
        return file.read(limit + 1)


def read_cached(path, limit):
    """read_private(path, limit) for a cache: None where there is no entry or it
    is untrusted (warned once: the program then compiles), b"" where it is unreadable or
    over the limit (damaged: the caller removes it)."""
    try:
        return read_private(path, limit)
    except Untrusted as err:
        warn_once(f"{err}; not loaded, the program is compiled")
        return None
    except (ValueError, OSError):
        return b""


def write_private(path, data):
    """Write `data` to `path` atomically (a temporary file of mode 0600, then a rename);
    OSError when it cannot be written (nothing is left behind)."""
    handle, temporary = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(temporary)
        raise
