"""Where plantdyn may write a file the user names: the one rule, for every writer.

A command that writes a file the user chose (``plantdyn export --out``, ``plantdyn runs
--plot``) asks :func:`safe_target` before any work and writes with
:func:`write_atomically`.  The rule:

* the target is a new name, or a **regular file** replaced only with ``force``; a FIFO, a
  device node, a socket, a directory or a symbolic link is never replaced nor written
  through (checked on ``os.lstat``, ``stat.S_ISREG``) — not even with ``force``;
* its folder exists, is a folder and is writable;
* it is not inside a run directory (a folder holding a plantdyn ``manifest.json``: the
  store's immutable results) and is not the results catalog (a name starting with
  ``catalog.sqlite``);
* every name in the path fits the file system (at most ``NAME_MAX`` bytes, commonly 255;
  the whole path at most ``PATH_MAX``);
* file names built from stored data (a run's job name and run id) use only the store's
  safe characters (:func:`safe_name`); anything else is refused (exit 2, not rewritten:
  a manifest naming ``"job": "../../x"`` was edited, and a silently changed name would
  hide that), so no built name escapes its folder.

The write itself is atomic (a temporary file beside the target, fsync, ``os.replace``)
and checks the rule again just before the rename, so a special file that appears in the
meantime is not replaced either.  Every refusal is a :class:`~pipeline.errors.ConfigError`
(or :class:`~pipeline.errors.StorageError` for an unwritable folder or a full disk):
one message naming the option, the path and the fix; exit 2 in the CLI.
"""

from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path

from pipeline.errors import ConfigError, StorageError

__all__ = ["check_path_length", "file_kind", "safe_name", "safe_target", "write_atomically"]

_KINDS = ((stat.S_ISFIFO, "FIFO (named pipe)"), (stat.S_ISCHR, "character device"),
          (stat.S_ISBLK, "block device"), (stat.S_ISSOCK, "socket"),
          (stat.S_ISDIR, "folder"), (stat.S_ISLNK, "symbolic link"),
          (stat.S_ISREG, "regular file"))
_MANIFEST_MAX_BYTES = 64 << 20
"""A ``manifest.json`` larger than this is not read when looking for run directories."""


def file_kind(mode: int) -> str:
    """What an ``os.lstat`` mode is, in words ("FIFO (named pipe)", "regular file", ...).

    Parameters
    ----------
    mode : int
        ``st_mode`` of ``os.lstat``.
    """
    return next((name for test, name in _KINDS if test(mode)), "special file")


def _limits(folder: Path) -> tuple[int, int]:
    """``(NAME_MAX, PATH_MAX)`` of the file system holding ``folder`` (255/4096 if the OS
    does not say)."""
    probe = next((p for p in (folder, *folder.parents) if os.path.isdir(p)), Path("/"))
    limits = []
    for key, default in (("PC_NAME_MAX", 255), ("PC_PATH_MAX", 4096)):
        try:
            limits.append(int(os.pathconf(probe, key)))
        except (OSError, ValueError, AttributeError):
            limits.append(default)
    return limits[0], limits[1]


def check_path_length(path: str | os.PathLike, option: str) -> Path:
    """``path`` as an absolute path, after checking its names fit the file system.

    Parameters
    ----------
    path : str or os.PathLike
        A path the user gave.
    option : str
        The option or argument it came from (``"--out"``, ``"STORAGE"``), for the message.

    Raises
    ------
    ConfigError
        A name in the path longer than the file system allows, or the whole path longer
        than ``PATH_MAX``.
    """
    text = os.fspath(path)
    if "\0" in text:
        raise ConfigError(f"{option} {text!r} contains a NUL character; give a plain path")
    target = Path(text).expanduser().absolute()
    name_max, path_max = _limits(target.parent)
    for name in target.parts:
        size = len(os.fsencode(name))
        if size > name_max:
            raise ConfigError(
                f"{option}: the name {name[:40]!r}… is {size} bytes long; a file or folder "
                f"name may have at most {name_max} bytes on this file system — give a "
                f"shorter {option}")
    size = len(os.fsencode(str(target)))
    if size > path_max:
        raise ConfigError(f"{option}: the path is {size} bytes long; at most {path_max} on "
                          f"this file system — give a shorter {option}")
    return target


def safe_name(parts: dict[str, str], *, suffix: str, where: str) -> str:
    """A file name joined from stored names (``<job>_<run-id>.csv``), each part checked as
    the store checks job names and run ids (letters, digits, ``_``, ``-``, ``.``; not
    starting with ``.``; at most 100 characters) — refused, not rewritten, otherwise.

    Parameters
    ----------
    parts : dict of str to str
        What each part is (``"job"``, ``"run_id"``) and its value; joined with ``_``.
    suffix : str
        The ending, e.g. ``".csv"``.
    where : str
        Where the parts come from, for the message (``"the run's manifest …"``).

    Raises
    ------
    ConfigError
        A part is not a safe name; the message names it and where it came from.
    """
    from pipeline.adapters.store import NAME_RE
    from pipeline.adapters.store.files import MAX_NAME_LENGTH

    for label, value in parts.items():
        if not isinstance(value, str) or len(value) > MAX_NAME_LENGTH or \
                not NAME_RE.fullmatch(value):
            raise ConfigError(
                f"{where} has {label} {str(value)[:60]!r}, which cannot be part of a file name "
                f"(only letters, digits, '_', '-' and '.', not starting with '.', at most "
                f"{MAX_NAME_LENGTH} characters); give the file with --out FILE")
    return "_".join(parts.values()) + suffix


def _enclosing_run(folder: Path) -> Path | None:
    """The run directory ``folder`` is (or is inside), if any: a folder with a plantdyn
    ``manifest.json`` (a JSON object with ``job``, ``run_id`` and ``files``)."""
    for candidate in (folder, *folder.parents):
        manifest = candidate / "manifest.json"
        try:
            st = manifest.lstat()
            if not stat.S_ISREG(st.st_mode) or st.st_size > _MANIFEST_MAX_BYTES:
                continue
            doc = json.loads(manifest.read_bytes())
        except (OSError, ValueError, RecursionError):
            continue
        if isinstance(doc, dict) and {"job", "run_id", "files"} <= set(doc):
            return candidate
    return None


def _refuse_existing(target: Path, option: str, force: bool, fix: str = "") -> None:
    """The rule on what is at ``target`` now (nothing, a regular file with ``force``)."""
    fix = fix or f"give another {option}"
    try:
        mode = target.lstat().st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise ConfigError(f"{option} {target}: cannot be checked ({exc.strerror or exc}); "
                          f"{fix}") from None
    if stat.S_ISLNK(mode):
        raise ConfigError(
            f"{option} {target} is a symbolic link (to {os.readlink(target)}); plantdyn "
            f"replaces only regular files — {fix}")
    if not stat.S_ISREG(mode):
        raise ConfigError(
            f"{option} {target} is a {file_kind(mode)}, not a regular file; plantdyn never "
            f"replaces or writes through one, even with --force — {fix}")
    if not force:
        raise ConfigError(f"{option} {target} exists; pass --force to replace it, or give "
                          f"another {option}")


def safe_target(path: str | os.PathLike, *, force: bool, option: str, fix: str = "") -> Path:
    """The absolute path of a file the user asked for, after the rule above.

    Parameters
    ----------
    path : str or os.PathLike
        The file (not a folder: a caller that accepts a folder appends its file name).
    force : bool
        Replace an existing regular file.
    option : str
        The option the path came from (``"--out"``, ``"--plot"``), for the messages.
    fix : str
        What the user can do when the target is refused (default "give another
        ``option``").

    Returns
    -------
    Path
        The absolute path to write with :func:`write_atomically`.

    Raises
    ------
    ConfigError
        The name is too long, the folder is missing, the target is inside a run directory
        or is the catalog, is not a regular file, or exists without ``force``.
    StorageError
        The folder is not writable.
    """
    from pipeline.adapters.store import CATALOG_NAME

    target = check_path_length(path, option)
    folder = target.parent
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise ConfigError(f"{option} {target}: the folder {folder} {what}; create it or give "
                          f"another {option}")
    run = _enclosing_run(folder)
    if run is not None:
        raise ConfigError(
            f"{option} {target} is inside the run directory {run}: run directories are the "
            "store's immutable results (every file is listed with its sha256 in "
            f"manifest.json); give an {option} outside the results' run folders")
    if target.name.startswith(CATALOG_NAME):
        raise ConfigError(f"{option} {target} would replace the results catalog "
                          f"({CATALOG_NAME}); give another file name")
    _refuse_existing(target, option, force, fix)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise StorageError(f"{option} {target}: the folder {folder} is not writable; give a "
                           f"writable folder with {option} — nothing was written")
    return target


def write_atomically(path: Path, data: bytes, *, option: str) -> Path:
    """Write ``data`` to a path :func:`safe_target` allowed: a temporary file beside it,
    fsync, then ``os.replace`` — after checking again that nothing but a regular file (or
    nothing) is there.  Nothing is left half-written.

    Parameters
    ----------
    path : Path
        From :func:`safe_target`.
    data : bytes
        The whole content.
    option : str
        The option the path came from, for the messages.

    Raises
    ------
    ConfigError
        A non-regular file appeared at ``path`` since it was checked.
    StorageError
        The write failed (disk full, permissions); nothing was written.
    """
    from pipeline.adapters.store.files import atomic_write_bytes

    _refuse_existing(path, option, force=True)
    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        if isinstance(exc, StorageError):
            raise
        full = exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1))
        cause = "the disk is full" if full else (exc.strerror or str(exc))
        raise StorageError(f"cannot write {path}: {cause}; give another {option} (a "
                           "writable folder with free space) — nothing was written") from None
    return path
