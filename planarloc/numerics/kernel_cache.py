"""Where numba keeps planarloc's compiled kernels, also on a read-only install.

numba compiles a ``cache=True`` kernel on its first call and keeps the machine code in an index
file (``*.nbi``) and data files (``*.nbc``). Its cache locators (``numba.core.caching``) choose the
folder for each kernel: ``NUMBA_CACHE_DIR`` if set; else ``__pycache__`` next to the module, but
only if numba can write there; else numba's user-wide folder in HOME (``~/.cache/numba``); else
none, and then defining the kernel fails (``RuntimeError: cannot cache function 'rays_invalid':
no locator available``). On a read-only install (a container image built as root and run as
another ``USER``, a system-wide install used by a service account) the kernels that
``planarloc warmup`` compiled at build time are therefore never read: each process compiles
about 70 kernels again (a minute of CPU), or, without a writable HOME, cannot import planarloc.

Importing this module (``planarloc/__init__.py`` does, before any kernel is defined) gives numba a
cache class, :class:`KernelCache`, that changes one case: a planarloc module whose ``__pycache__``
numba cannot write. For its kernels the cache

- reads the ``__pycache__`` next to the module, read-only (the install's warm cache: its index
  and data files only need to be readable), then this user's folders below;
- writes a kernel compiled now to the first of: numba's user-wide folder (HOME, as numba would),
  this user's temp folder ``<temp>/planarloc-<uid>/kernels`` (mode 0700, checked:
  :mod:`planarloc.numerics.user_folders`), or, where neither can be written, nowhere: the kernel
  is then compiled in memory in each process. A fallback to the temp folder or to memory is
  said in one warning line per process, when the first kernel is compiled.

Wherever planarloc's kernels are cached, an index or data file that cannot be unpickled counts as
a cache miss (:class:`_TolerantIndexFile`): numba unpickles a kernel's index before it compares
the source stamp, so an index written by another planarloc version (or an edited checkout) that
names a type which no longer exists raised ``AttributeError`` from the kernel's first call, and
again from every call that tried to save it; now the kernel compiles and its index is written
anew.

Everything else stays numba's own behaviour: ``NUMBA_CACHE_DIR`` and ``NUMBA_CACHE_LOCATOR_CLASSES``
take precedence, a writable install caches in ``__pycache__``, other packages' kernels are not
touched. How: ``Dispatcher.enable_caching`` (``@njit(cache=True)``) creates the cache as
``numba.core.dispatcher.FunctionCache(py_func)``; this module points that name at
:class:`KernelCache`, a subclass that is numba's class unless the case above applies. Written
against numba 0.59-0.68's ``numba.core.caching`` (the locator and cache class names changed in
between; both spellings are looked up).
"""

from __future__ import annotations

import functools
import inspect
import logging
import os
import tempfile
import threading
from typing import TYPE_CHECKING

from numba.core import caching, config, dispatcher

from planarloc.numerics.user_folders import UnsafeFolderError, user_temp_folder, user_temp_root

__all__ = ["KernelCache", "cache_folders", "install", "kernels_persist"]

logger = logging.getLogger(__name__)

#: The planarloc package folder: only kernels of modules below it are handled here.
PACKAGE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The subfolder of this user's temp folder that holds kernels (:func:`user_temp_folder`).
TEMP_SUBFOLDER = "kernels"


def _numba_class(*names: str) -> type:
    for name in names:
        cls = getattr(caching, name, None)
        if cls is not None:
            return cls
    raise ImportError(f"numba.core.caching has none of {', '.join(names)}: a numba this module does not know")


if TYPE_CHECKING:  # the type checker sees the current numba's names; at run time both spellings are looked up
    from numba.core.caching import CompileResultCacheImpl as _CompileResultImpl
    from numba.core.caching import IndexDataCacheFile as _IndexDataFile
    from numba.core.caching import InTreeCacheLocator as _InTreeLocator
    from numba.core.caching import UserWideCacheLocator as _UserWideLocator
else:
    _InTreeLocator = _numba_class("InTreeCacheLocator", "_InTreeCacheLocator")
    _UserWideLocator = _numba_class("UserWideCacheLocator", "_UserWideCacheLocator")
    _CompileResultImpl = _numba_class("CompileResultCacheImpl")
    _IndexDataFile = _numba_class("IndexDataCacheFile")
_FunctionCache = caching.FunctionCache  # numba's class, kept whatever dispatcher.FunctionCache is set to


class _InstalledTreeLocator(_InTreeLocator):
    """numba's in-tree locator (``__pycache__`` next to the module) without its test that the
    folder is writable: the folder is only read (:class:`_LayeredCacheFile` decides where to write)."""

    def ensure_cache_path(self) -> None:  # numba calls it before each save; saves never go here
        pass

    @classmethod
    def from_function(cls, py_func, py_file):
        return cls(py_func, py_file) if os.path.exists(py_file) else None


class _InstalledTreeImpl(_CompileResultImpl):
    _locator_classes = [_InstalledTreeLocator]


@functools.cache
def _tree_writable(folder: str) -> bool:
    """Whether numba's own in-tree locator would take ``folder/__pycache__`` (its own test)."""
    return _writable(os.path.join(folder, "__pycache__"), private=False)


def _planarloc_source(py_func) -> str | None:
    """The source file of a planarloc kernel; None for every other kernel."""
    try:
        source = os.path.abspath(inspect.getfile(py_func))
    except TypeError:
        return None
    return source if source.startswith(PACKAGE_ROOT + os.sep) and os.path.exists(source) else None


def _read_only_module(py_func) -> str | None:
    """The source file of a planarloc kernel whose ``__pycache__`` numba cannot write (and no
    ``NUMBA_CACHE_DIR`` or locator override is set); None for every other kernel."""
    if getattr(config, "CACHE_DIR", "") or getattr(config, "CACHE_LOCATOR_CLASSES", ""):  # set at run time
        return None
    source = _planarloc_source(py_func)
    if source is None:
        return None
    return None if _tree_writable(os.path.dirname(source)) else source


class _TolerantIndexFile(_IndexDataFile):
    """numba's index and data files of one kernel, where a file that cannot be unpickled counts
    as missing: the kernel is compiled and, on save, the index is written anew (module docstring).
    Read errors of the file system (``OSError``) stay numba's."""

    def _load_index(self) -> dict:
        try:
            return super()._load_index()
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - unpickling a stale or damaged index: a cache miss
            logger.info("kernel cache index %s unreadable (%s): compiled again", self._index_path, exc)
            return {}

    def _load_data(self, name):
        try:
            return super()._load_data(name)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - numba's load() then compiles, as for a missing file
            raise OSError(f"kernel cache data {name} unreadable ({exc})") from exc


# ---- one line per process ----------------------------------------------------------------------------
_said = threading.Lock()
_told = False


def _say_once(level: int, message: str, *args: object) -> None:
    """Log the first fallback of this process (later kernels fall back the same way, silently)."""
    global _told
    with _said:
        if _told:
            return
        _told = True
    logger.log(level, message, *args)


# ---- where a kernel compiled now is written ------------------------------------------------------------
@functools.cache
def _temp_folder_problem() -> str | None:
    """None if this user's temp folder for kernels can be used (it is created), else why not."""
    try:
        user_temp_folder(TEMP_SUBFOLDER)
    except UnsafeFolderError as exc:
        return str(exc)
    except OSError as exc:
        return f"no writable temp folder ({exc.strerror or exc})"
    return None


_trusted = False


def _temp_folder_trusted() -> bool:
    """Whether this user's temp folder for kernels exists and may be read (its files are pickles:
    a folder another user could write to is never read). Checked until it is found sound."""
    global _trusted
    if not _trusted:
        try:
            _trusted = os.path.isdir(user_temp_folder(TEMP_SUBFOLDER, create=False))
        except (OSError, ValueError):
            return False
    return _trusted


def _writable(path: str, private: bool) -> bool:
    """Whether a file can be made in ``path`` (created first: mode 0700 when ``private``, and
    then never through a symbolic link)."""
    try:
        if private:
            os.makedirs(path, mode=0o700, exist_ok=True)
            if os.path.islink(path):
                return False
        else:
            os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


class _LayeredCacheFile:
    """numba's ``IndexDataCacheFile`` over several folders: loads a kernel from the first that holds
    it (the install's ``__pycache__`` first), saves to the first writable user folder, or nowhere."""

    def __init__(self, installed, filename_base: str, source_stamp, home: str, temp: str, tree: str) -> None:
        self._installed = installed
        self._base, self._stamp = filename_base, source_stamp
        self._home, self._temp, self._tree = home, temp, tree
        self._files: dict[str, object] = {}
        self._writer: object | None = None
        self._chosen = False
        self._note: tuple = (logging.DEBUG, "")

    def _file(self, path: str):
        if path not in self._files:
            self._files[path] = _TolerantIndexFile(
                cache_path=path, filename_base=self._base, source_stamp=self._stamp
            )
        return self._files[path]

    def folders(self) -> list[str]:
        """The folders read, in order: the install's ``__pycache__``, then the user folders that exist."""
        out = [self._installed._cache_path]
        if os.path.isdir(self._home):
            out.append(self._home)
        if _temp_folder_trusted() and os.path.isdir(self._temp):
            out.append(self._temp)
        return out

    def _readable(self):
        yield self._installed
        for path in self.folders()[1:]:
            yield self._file(path)

    def load(self, key):
        for f in self._readable():
            try:
                data = f.load(key)
            except Exception as exc:  # noqa: BLE001 - a damaged cache file: compile instead
                logger.debug("kernel cache %s unreadable (%s)", f._index_path, exc)
                continue
            if data is not None:
                return data
        return None

    def _load_index(self) -> dict:
        """Every signature key held in any folder (what ``planarloc warmup`` looks up)."""
        merged: dict = {}
        for f in reversed(list(self._readable())):
            try:
                merged.update(f._load_index())
            except Exception:  # noqa: BLE001 - unreadable: as if empty
                continue
        return merged

    def writer(self):
        """The cache file kernels compiled now are saved to, or None (in memory only); chosen once,
        silently (:meth:`save` says it, with the first kernel compiled)."""
        if not self._chosen:
            self._chosen = True
            if _writable(self._home, private=False):
                self._writer = self._file(self._home)
                self._note = (
                    logging.INFO,
                    "%s is read-only: planarloc's kernels compiled now are cached in %s",
                    self._tree,
                    os.path.dirname(self._home),
                )
            elif _temp_folder_problem() is None and _writable(self._temp, private=True):
                self._writer = self._file(self._temp)
                self._note = (
                    logging.WARNING,
                    "%s is read-only and HOME is not writable: planarloc's kernels "
                    "compiled now are cached in %s",
                    self._tree,
                    os.path.dirname(self._temp),
                )
            else:
                why = _temp_folder_problem() or f"{self._temp} is not writable"
                self._note = (
                    logging.WARNING,
                    "%s is read-only, HOME is not writable and %s: planarloc's kernels "
                    "compiled now stay in memory (compiled again in each process); run `planarloc "
                    "warmup` where the install is writable, or set NUMBA_CACHE_DIR to a writable folder",
                    self._tree,
                    why,
                )
        return self._writer

    def save(self, key, data) -> None:
        writer = self.writer()
        _say_once(*self._note)
        if writer is None:
            return
        try:
            writer.save(key, data)
        except OSError as exc:  # e.g. the disk filled up: the kernel is compiled, only not kept
            logger.info("kernel cache %s: not saved (%s)", writer._cache_path, exc)

    def flush(self) -> None:
        writer = self.writer()
        if writer is not None:
            writer.flush()


class KernelCache(_FunctionCache):
    """numba's ``FunctionCache``, except for planarloc's kernels: files that cannot be unpickled
    are cache misses, and where the module's ``__pycache__`` numba cannot write, it reads that
    folder and this user's folders, and writes to the first writable user folder (module docstring)."""

    def __init__(self, py_func) -> None:
        source = _read_only_module(py_func)
        if source is not None:
            self._impl_class = _InstalledTreeImpl
        super().__init__(py_func)
        self.read_only_install = source is not None
        if source is None and _planarloc_source(py_func) is not None:
            self._cache_file = _TolerantIndexFile(
                cache_path=self._cache_path,
                filename_base=self._impl.filename_base,
                source_stamp=self._impl.locator.get_source_stamp(),
            )
        if source is not None:
            subpath = _InTreeLocator.get_suitable_cache_subpath(source)
            home = _UserWideLocator(py_func, source).get_cache_path()
            try:
                temp = os.path.join(user_temp_root(), TEMP_SUBFOLDER, subpath)
            except OSError:  # no usable temp folder at all
                temp = os.path.join(os.sep, "nonexistent", TEMP_SUBFOLDER, subpath)
            self._cache_file = _LayeredCacheFile(
                self._cache_file,
                self._impl.filename_base,
                self._impl.locator.get_source_stamp(),
                home,
                temp,
                os.path.dirname(self._cache_path),
            )


def cache_folders(cache) -> list[str]:
    """The folders a dispatcher's cache (``Dispatcher._cache``) reads its kernels from."""
    layered = getattr(cache, "_cache_file", None)
    if isinstance(layered, _LayeredCacheFile):
        return layered.folders()
    path = getattr(cache, "cache_path", None)
    return [path] if path else []


def kernels_persist(cache) -> bool:
    """Whether a kernel compiled now for this dispatcher's cache is kept on disk (for other
    processes); False when it would only be compiled in memory."""
    layered = getattr(cache, "_cache_file", None)
    if isinstance(layered, _LayeredCacheFile):
        return layered.writer() is not None
    return hasattr(cache, "_cache_file")


def install() -> None:
    """Make numba create the caches of ``cache=True`` kernels with :class:`KernelCache` (idempotent;
    done on import)."""
    dispatcher.FunctionCache = KernelCache  # type: ignore[attr-defined]  # numba's dispatcher.pyi omits it


install()
