"""Atomic file writes: a temporary file beside the target, renamed over it only when complete.

The one place skyfit creates output files, so that a failure (or a kill) never leaves a partial
file under the target's name (CONTRACT.md, "Errors"). ``tempfile.mkstemp`` creates its file
with mode 0600; the result gets the mode a plain ``open(path, "w")`` would give (0666 less
the umask), so outputs stay readable by the user's group as usual.

Temporary names carry the writer's process id, ``.<name>.skyfit-<pid>-<random><suffix>``, so that
the temporaries of a killed run (SIGKILL leaves them; any other ending removes them) are
recognised and removed by the next write into the same folder (:func:`remove_stale`,
docs/reliability.md). :func:`check_writable` lets a command refuse an output path before
its work rather than after.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterator

TEMP_TAG = ".skyfit-"
"""Marks skyfit's temporaries: ``.<target name>.skyfit-<pid>-<random><suffix>``."""
_TEMP_RE = re.compile(r"^\..+\.skyfit-(\d+)-[A-Za-z0-9_]+\.tmp(\.[A-Za-z0-9]+)?$")
_LEGACY_TEMP_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")
LEGACY_STALE_AFTER_S: float = 3600.0
"""Temporaries of skyfit versions before the process id was in their name (``.<name>.<random>.tmp``)
count as stale once this old [s]."""
_SCANNED: set[str] = set()


class OutputError(ValueError):
    """An output path that cannot be written: one line naming it (CONTRACT.md, "Errors")."""


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it exists, owned by someone else
        return True
    return True


def remove_stale(folder: str | Path) -> list[str]:
    """Remove the temporaries a killed skyfit run left in ``folder``; the names removed.

    A temporary is stale when the process named in it no longer runs (on this machine), or, for
    the older names without a process id, when it is :data:`LEGACY_STALE_AFTER_S` old.
    Temporaries of running writers are left alone. Each folder is scanned once per process.
    """
    folder = Path(folder)
    key = str(folder.resolve()) if folder.exists() else str(folder)
    if key in _SCANNED or not folder.is_dir():
        return []
    _SCANNED.add(key)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    now = time.time()
    for e in entries:
        m = _TEMP_RE.match(e.name)
        if m:
            stale = not _alive(int(m.group(1)))
        elif _LEGACY_TEMP_RE.match(e.name):
            try:
                stale = now - e.stat(follow_symlinks=False).st_mtime > LEGACY_STALE_AFTER_S
            except OSError:
                stale = False
        else:
            continue
        if not stale:
            continue
        try:
            if e.is_dir(follow_symlinks=False):
                shutil.rmtree(e.path)
            else:
                os.unlink(e.path)
            removed.append(e.name)
        except OSError:
            pass
    return removed


def temp_prefix(path: str | Path) -> str:
    """The name prefix of this process's temporaries for ``path`` (see the module docstring)."""
    return f".{Path(path).name}{TEMP_TAG}{os.getpid()}-"


def _existing_ancestor(folder: Path) -> Path:
    p = folder
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def check_writable(path: str | Path, *, directory: bool = False, what: str = "--out") -> Path:
    """``path`` as a Path when an output can be written there; OutputError naming it otherwise.

    Checks, creating nothing that stays: a file target is not an existing folder, a folder target
    not an existing file; the nearest existing folder on the way is a folder, and a file can be
    created in it (a probe file, removed at once). Folders still missing are left to the writer.

    Args:
        path: the file (or, with ``directory``, the folder) a command will write.
        directory: the target is a folder.
        what: how the message names the path (a flag, e.g. ``--out``).
    """
    path = Path(path)
    if directory:
        if os.path.lexists(path) and not path.is_dir():
            raise OutputError(f"{what} {path} exists and is not a directory")
        folder = path
    else:
        if path.is_dir():
            raise OutputError(f"{what} {path} is a directory; give a file name")
        folder = path.parent
    anc = _existing_ancestor(folder)
    if not anc.is_dir():
        raise OutputError(f"{what} {path}: cannot write there: {anc} is not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".skyfit-probe-", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise OutputError(f"{what} {path}: cannot write in {anc} ({e.strerror or e})") from None
    return path


def make_temp_dir(path: str | Path) -> Path:
    """A temporary folder beside ``path`` (created with its parents) for a folder written at once."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale(path.parent)
        return Path(tempfile.mkdtemp(prefix=temp_prefix(path), suffix=".tmp", dir=path.parent))
    except OSError as e:
        raise OutputError(f"cannot write {path}: {e.strerror or e}") from None


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write; on success it replaces ``path``.

    Creates the parent folder. On any exception the temporary file is removed and the
    exception propagates; ``path`` is untouched.
    """
    path = Path(path)
    if not suffix.startswith(".tmp"):
        raise ValueError(f"atomic_path: suffix must start with '.tmp' (stale temporaries are found by it), got {suffix!r}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:  # name the target, not a temporary (CONTRACT.md)
        raise OutputError(f"cannot write {path}: {e.strerror or e}") from None
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except OSError as e:
        if e.filename in (tmp, str(tmp)) or e.filename2 in (tmp, str(tmp), str(path)):
            raise OutputError(f"cannot write {path}: {e.strerror or e}") from None
        raise
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`atomic_path`)."""
    return write_bytes_atomic(path, text.encode("utf-8"))
