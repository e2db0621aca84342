"""Atomic file writes: a reader sees the old file or the new one, never half of one."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def atomic_write_bytes(
    path: str | Path, data: bytes, previous: str | Path | None = None, file_mode: int | None = None
) -> None:
    """Write ``data`` to ``path`` atomically; with ``previous``, the file it replaces is kept there (moved
    only once the new one is complete on disk, so a write that fails, e.g. a full disk, leaves both).
    ``file_mode`` (e.g. 0o600 for a private key) instead of a new file's usual mode."""
    with atomic_writer(path, "wb", previous=previous, file_mode=file_mode) as f:
        f.write(data)


@contextlib.contextmanager
def atomic_writer(path: str | Path, mode: str = "w", previous: str | Path | None = None, file_mode: int | None = None):
    """Write to a temp file beside ``path``, fsync, then rename over it (POSIX-atomic); ``previous`` and
    ``file_mode``: see ``atomic_write_bytes``. An ``OSError`` (a full disk: ENOSPC) names ``path``; the old
    file is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    if file_mode is None:
        umask = os.umask(0)
        os.umask(umask)
        file_mode = 0o666 & ~umask  # mkstemp creates 0600; the result should read like any new file
    os.chmod(tmp, file_mode)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if previous is not None and path.exists():
            _keep_as(path, Path(previous))
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(err, OSError) and err.filename is None:
            # write() and fsync() errors carry no file name; a run's error should say which file
            raise OSError(err.errno, err.strerror, str(path)) from err
        raise


def _keep_as(path: Path, previous: Path) -> None:
    """Put ``path``'s file at ``previous`` too, ``path`` staying in place until the new file is renamed over
    it: a hard link renamed onto ``previous``. (Renaming ``path`` itself left a moment with no file under
    its name: a writer killed then left only the older one.) Without hard links, the plain rename."""
    link = previous.with_name(f".{previous.name}.link")
    with contextlib.suppress(FileNotFoundError):
        os.unlink(link)  # a leftover of a writer killed between the link and the rename
    try:
        os.link(path, link)
    except OSError:  # a file system without hard links
        os.replace(path, previous)
        return
    os.replace(link, previous)
