"""This user's folder in the shared temp folder, which another local user cannot aim.

The system temp folder (``/tmp``, or ``TMPDIR``) is shared by every local user. A fixed name in it
(``/tmp/planarloc-bags``) can be taken first by someone else: as a symbolic link to one of the
victim's folders, or as a folder of theirs that they can fill. A program that trusts the name then
reads, writes or deletes where that other user chose. So planarloc keeps what it caches in the temp
folder under ``<temp folder>/planarloc-<uid>`` (:func:`user_temp_folder`): created with mode 0700
and used only while it is a real folder (not a symbolic link), owned by this user and closed to
others. Otherwise :class:`UnsafeFolderError` says what is wrong in one line.

Used by the kernel cache (:mod:`planarloc.numerics.kernel_cache`) and the map and bag caches
(:func:`planarloc.map.settings.cache_dir`).
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

__all__ = ["UnsafeFolderError", "check_private_folder", "user_temp_folder", "user_temp_root"]


class UnsafeFolderError(PermissionError):
    """A folder planarloc would keep its own files in is a symbolic link, is not a folder, belongs to
    another user, or is open to other users."""


def _owner(uid: int) -> str:
    try:
        import pwd

        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except (ImportError, KeyError):
        return f"uid {uid}"


def check_private_folder(path: str | os.PathLike) -> None:
    """Raise :class:`UnsafeFolderError` unless ``path`` is a real folder (not a symbolic link) of
    this user that no other user can write to. Read permissions for others are removed.

    Raises:
        UnsafeFolderError: what is wrong, and what to do (one line).
        FileNotFoundError: there is no such folder.
    """
    path = Path(path)
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise UnsafeFolderError(
            f"{path} is a symbolic link (to {os.readlink(path)}), not a folder of yours; "
            "planarloc does not follow it: remove it, or set TMPDIR to a folder of yours"
        )
    if not stat.S_ISDIR(st.st_mode):
        raise UnsafeFolderError(f"{path} is not a folder; remove it, or set TMPDIR to a folder of yours")
    if st.st_uid != os.geteuid():
        raise UnsafeFolderError(
            f"{path} belongs to {_owner(st.st_uid)}, not to you ({_owner(os.geteuid())}); "
            "planarloc does not use it: remove it, or set TMPDIR to a folder of yours"
        )
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise UnsafeFolderError(
            f"{path} can be written by other users (mode {stat.S_IMODE(st.st_mode):o}); "
            "planarloc does not use it: remove it, or set TMPDIR to a folder of yours"
        )
    if st.st_mode & 0o077:
        os.chmod(path, stat.S_IMODE(st.st_mode) & 0o700)


def user_temp_root() -> Path:
    """``<temp folder>/planarloc-<uid>``: the path only (nothing is created or checked)."""
    return Path(tempfile.gettempdir()) / f"planarloc-{os.geteuid()}"


def user_temp_folder(*parts: str, create: bool = True) -> Path:
    """This user's folder ``<temp folder>/planarloc-<uid>/<parts...>``, checked with
    :func:`check_private_folder` at every level (created with mode 0700 if ``create``; without
    ``create``, a missing folder is returned unchecked).

    Raises:
        UnsafeFolderError: the folder, or one above it up to ``planarloc-<uid>``, is a symbolic
            link, not a folder, another user's, or writable by others.
        OSError: it cannot be created (e.g. no writable temp folder).
    """
    for name in parts:
        if name in ("", ".", "..") or os.sep in name:
            raise ValueError(f"user_temp_folder: {name!r} is not a folder name")
    root = user_temp_root()
    levels = [root.joinpath(*parts[:k]) for k in range(len(parts) + 1)]
    for level in levels:
        if create:
            try:
                os.mkdir(level, 0o700)
            except FileExistsError:
                pass
        elif not os.path.lexists(level):
            return levels[-1]
        check_private_folder(level)
    return levels[-1]
