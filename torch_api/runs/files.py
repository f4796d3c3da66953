"""Result files written atomically and never through a symbolic link (reports, tables, figures).

A file is written whole to a temporary file in its own folder (``PATH.<pid>.new``), synced,
and renamed onto ``PATH`` (the folder synced too): a kill or a full disk at any instant leaves
the old file or the new one, never a torn one. The destination and the temporary name must not
be symbolic links: a link planted there (pointing at a file elsewhere) is refused with one line
naming it, and nothing is written anywhere. Only the last component is checked; a folder on the
way may be a link (``/tmp`` on some systems is one).

One writer per file at a time (the examples hold their folder's lock).

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_text_atomic(Path(d) / "results.json", '{"J": 0.5}')
    ...     (Path(d) / "results.json").read_text()
    '{"J": 0.5}'
"""

from __future__ import annotations

import contextlib
import io
import os
import stat
from pathlib import Path

from torch_api.runs.store_errors import SymlinkRefusedError

__all__ = [
    "SymlinkRefusedError",
    "save_figure_atomic",
    "temporary_name",
    "write_bytes_atomic",
    "write_text_atomic",
]


def temporary_name(path: str | os.PathLike) -> Path:
    """The temporary file that :func:`write_bytes_atomic` writes before renaming it onto
    ``path``: ``PATH.<pid>.new``, in the same folder."""
    path = Path(path)
    return path.with_name(f"{path.name}.{os.getpid()}.new")


def _refuse_link(path: Path, destination: Path) -> None:
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if stat.S_ISLNK(mode):
        raise SymlinkRefusedError(
            f"{path} is a symbolic link; {destination} is never written through one (remove "
            "the link, or write elsewhere)"
        )


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename, folder fsync).

    Raises:
        SymlinkRefusedError: ``path`` or its temporary name is a symbolic link (nothing is
            written).
        OSError: the file cannot be written (the old file, if any, is left as it was).
    """
    path = Path(path)
    temporary = temporary_name(path)
    _refuse_link(path, path)
    _refuse_link(temporary, path)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(temporary)  # left by a writer killed before its rename (not a link: checked)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(temporary, flags, 0o644)
    except FileExistsError:  # planted between the check and the open
        _refuse_link(temporary, path)
        raise
    try:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        _refuse_link(path, path)  # (a rename replaces a link, never writes through it)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    _fsync_folder(path.parent)


def write_text_atomic(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically, as :func:`write_bytes_atomic`."""
    write_bytes_atomic(path, text.encode(encoding))


def save_figure_atomic(figure, path: str | os.PathLike, **savefig) -> None:
    """Save a matplotlib ``figure`` to ``path`` atomically, as :func:`write_bytes_atomic`:
    drawn into memory first (format from the suffix unless ``format=`` is given; other
    keywords go to ``figure.savefig``), then written."""
    path = Path(path)
    savefig.setdefault("format", path.suffix.lstrip(".").lower() or "png")
    buffer = io.BytesIO()
    figure.savefig(buffer, **savefig)
    write_bytes_atomic(path, buffer.getvalue())


def _fsync_folder(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
