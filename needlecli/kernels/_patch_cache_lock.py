"""numba patch: saves to the on-disk cache under a file lock.

numba saves a compiled function by reading its cache index, adding the entry and writing the index back.
Two processes compiling the same function at once (a first run compiles in two processes:
:func:`needlecli.kernels.warm_up`) can then lose an entry, or overwrite each other's data file; numba
does not lock its cache (numba/numba#4807, caches written in parallel; numba/numba#10128, where the
maintainers proposed a file lock). Each save here holds an exclusive lock on a file beside the index
(:func:`needlecli.platform.file_lock`: ``flock`` where the platform has it, else its fallback), so that saves of one function follow one another; loads are unchanged (the index and
data files are replaced atomically). Drop when numba locks its cache saves itself.
"""

from __future__ import annotations


def locked_cache_saves() -> None:
    """Wrap ``IndexDataCacheFile.save`` in an exclusive lock (once per process)."""
    from numba.core import caching

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


locked_cache_saves()
