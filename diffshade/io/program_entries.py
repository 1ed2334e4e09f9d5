"""The program store's entries (diffshade.io.compile_cache): one file per program,
`programs/<environment key>/<hash of the call>.bin` in the cache folder.

    write_entry(path, key, compiled, device)     # compiled None: "call jit" for this key
    program = read_entry(path, key, in_tree, device)   # Compiled, PLAIN, or None

An entry is a line naming the format (MAGIC), a line of JSON and XLA's executable:

    {"key": [environment key, description of the call], "program": a description of the
     Compiled program (diffshade.io.executables) or null, "code_bytes": n,
     "code_sha256": hex}

Nothing is unpickled: the description is data, the executable goes to XLA's deserializer
only. The key is compared with the call's, so an entry renamed or copied onto another
program's name is not loaded; the length and SHA-256 find damage. Such an entry, one over
MAX_ENTRY_BYTES (refused before it is read) or one that cannot be rebuilt is removed, so
that the program is compiled and written again. Entries and folders that another user
could have written are refused with a warning (diffshade.io.private_files).
"""

import contextlib
import hashlib
import json
import os
import shutil

from diffshade.io import executables
from diffshade.io.private_files import (
    MAX_ENTRY_BYTES,
    Untrusted,
    check_folder,
    private_folder,
    read_cached,
    warn_once,
    write_private,
)

__all__ = ["MAGIC", "PLAIN", "read_entry", "remove", "write_entry"]

MAGIC = b"diffshade-program 2\n"
PLAIN = "plain jit"  # what read_entry gives for a key whose calls go to jit


def _entry_bytes(key, header=None, code=b""):
    """An entry's content; header None: the key's calls go to jit (no executable)."""
    head = {"key": key, "program": header, "code_bytes": len(code),
            "code_sha256": hashlib.sha256(code).hexdigest()}
    return MAGIC + json.dumps(head, allow_nan=False).encode() + b"\n" + code


def _parse_entry(blob, key):
    """(header, code) of an entry of `key`; ValueError when it is another key's or
    damaged."""
    if not blob.startswith(MAGIC):
        raise ValueError("not a program entry")
    line, _, code = blob[len(MAGIC):].partition(b"\n")
    head = json.loads(line)
    if not isinstance(head, dict) or head.get("key") != key:
        raise ValueError("an entry of another program")
    if head.get("code_bytes") != len(code) or \
            head.get("code_sha256") != hashlib.sha256(code).hexdigest():
        raise ValueError("a damaged executable")
    return head["program"], code


def remove(path):
    with contextlib.suppress(OSError):
        os.remove(path)


_folders = {}  # folder -> whether it is private (checked once per process)


def _trusted(folder) -> bool:
    """Whether the store's `folder` (and `programs` above it) may be used; warns once if
    not. A folder not there yet is trusted (private_folder creates it so)."""
    if folder not in _folders:
        try:
            for path in (os.path.dirname(folder), folder):
                if os.path.exists(path):
                    check_folder(path)
            _folders[folder] = True
        except (Untrusted, OSError) as err:
            warn_once(f"{err}; the program store is not used, programs compile normally")
            _folders[folder] = False
    return _folders[folder]


def read_entry(path, key, in_tree, device):
    """The Compiled program stored at path for `key`, PLAIN for a key whose calls go to
    jit, or None when there is none or it cannot be used: an untrusted entry is left (with
    a warning), a damaged or another key's entry is removed, to be written anew."""
    if not _trusted(os.path.dirname(path)):
        return None
    blob = read_cached(path, MAX_ENTRY_BYTES)
    if blob is None:
        return None
    try:
        header, code = _parse_entry(blob, key)
        if header is None:
            return PLAIN
        return executables.rebuild(header, code, in_tree, device)
    except Exception:  # any damage (XLA's deserializer has its own errors): compile afresh
        remove(path)
        return None


def _entry_of(key, compiled, device):
    """The entry of `compiled` (None, or one that cannot be described or is over the
    limit: an entry that sends the key's calls to jit)."""
    if compiled is not None:
        # Unstorable, or anything a JAX whose internals differ raises: not kept either
        with contextlib.suppress(Exception):
            blob = _entry_bytes(key, *executables.describe(compiled, device))
            if len(blob) <= MAX_ENTRY_BYTES:
                return blob
    return _entry_bytes(key)


def write_entry(path, key, compiled, device):
    """Write the entry of `compiled` (None: of jit's) to path, atomically (mode 0600); an
    untrusted folder, and a full or read-only disk, are skipped."""
    folder = os.path.dirname(path)
    if not _trusted(folder):
        return
    blob = _entry_of(key, compiled, device)
    try:
        fresh = not os.path.isdir(folder)
        private_folder(folder)
        if fresh:  # programs of other sources or versions are never read again
            store = os.path.dirname(folder)
            for name in os.listdir(store):
                other = os.path.join(store, name)
                if other != folder and len(name) == 64 and os.path.isdir(other):
                    shutil.rmtree(other, ignore_errors=True)
        write_private(path, blob)
    except (Untrusted, OSError):
        return
