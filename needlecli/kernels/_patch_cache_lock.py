"""numba patch: saves to the on-disk cache under a file lock, and each compilation under one too.

numba saves a compiled function by reading its cache index, adding the entry and writing the index back.
Two processes compiling the same function at once (a first run compiles in two processes:
:func:`needlecli.kernels.warm_up`; the workers of a sweep) can then lose an entry, or overwrite each
other's data file; numba does not lock its cache (numba/numba#4807, caches written in parallel;
numba/numba#10128, where the maintainers proposed a file lock). Each save here holds an exclusive lock on
a file beside the index (:func:`needlecli.platform.file_lock`: ``flock`` where the platform and the file
system have it, else its fallback), so that saves of one function follow one another; loads are unchanged
(the index and data files are replaced atomically).

And numba compiles what its cache lacks in every process that asks: the workers of a sweep on a cluster,
each starting on an empty cache, compile the same kernels at the same time (every one of them, on every
node). Here a process that does not find a function (with its signature) in the cache takes a lock
beside its index (``<index>.<signature hash>.compiling``) and looks again once it holds it: the process
that held it before has saved the function meanwhile, and this one loads it instead of compiling it. So
each kernel is compiled once per cache, however many processes (on however many machines sharing the
cache's folder) ask for it at once; processes that need different kernels compile them side by side.
Only needlecli's own cache folder is locked so (:mod:`needlecli.kernels._cache`), never another numba
user's. Drop when numba locks its cache saves and compilations itself.
"""

from __future__ import annotations

import hashlib
import os

_HELD: dict[tuple[int, str], object] = {}  # (cache, signature) -> the compile lock held while it compiles


def _ours(cache) -> bool:
    from needlecli.kernels import _cache

    try:
        return bool(getattr(cache, "_enabled", False)) and os.path.realpath(cache._cache_path).startswith(
            os.path.realpath(_cache.cache_dir()))
    except (AttributeError, OSError, TypeError):
        return False


def _release(cache, sig) -> None:
    held = _HELD.pop((id(cache), str(sig)), None)
    if held is not None:
        held.__exit__(None, None, None)


def locked_cache_saves() -> None:
    """Wrap ``IndexDataCacheFile.save`` in an exclusive lock, and each compilation of a function of
    needlecli's cache in its own (once per process)."""
    from numba.core import caching, dispatcher

    from needlecli.platform import file_lock

    cls = caching.IndexDataCacheFile
    if getattr(cls.save, "_needlecli_locked", False):
        return
    plain = cls.save

    def save(self, key, data):
        with file_lock(self._index_path + ".lock"):
            return plain(self, key, data)

    save._needlecli_locked = True
    cls.save = save

    cache_cls = caching.Cache
    plain_load, plain_save = cache_cls.load_overload, cache_cls.save_overload

    def load_overload(self, sig, target_context):
        cres = plain_load(self, sig, target_context)
        key = (id(self), str(sig))
        if cres is not None or key in _HELD or not _ours(self):
            return cres
        tag = hashlib.sha256(str(sig).encode()).hexdigest()[:12]
        lock = file_lock(f"{self._cache_file._index_path}.{tag}.compiling")
        lock.__enter__()  # (numba's compiler lock is held: taken in this order only, so no deadlock)
        try:
            cres = plain_load(self, sig, target_context)  # saved meanwhile by the process that held the lock
        except BaseException:
            lock.__exit__(None, None, None)
            raise
        if cres is not None:
            lock.__exit__(None, None, None)
            return cres
        _HELD[key] = lock  # released once saved, or when the compilation fails
        return None

    def save_overload(self, sig, data):
        try:
            return plain_save(self, sig, data)
        finally:
            _release(self, sig)

    disp_cls = dispatcher.Dispatcher
    plain_compile = disp_cls.compile

    def compile(self, sig):
        try:
            return plain_compile(self, sig)
        finally:
            cache = getattr(self, "_cache", None)
            if cache is not None and _HELD:
                _release(cache, sig)

    cache_cls.load_overload, cache_cls.save_overload, disp_cls.compile = load_overload, save_overload, compile


locked_cache_saves()
