"""The command-line programs' memory allocator settings (glibc), set once at start-up.

A patch build allocates and frees arrays of a few kB to tens of MB all the time. glibc's
defaults map the larger ones with ``mmap`` and give freed heap memory back to the system
above a small threshold, so the same pages are faulted in and zeroed again for the next
array: a third of a patch build's system CPU, ~8% of the whole (2.9 s of 18 s on a
36-cell patch from 108 files, 1.5 s with these settings, the same peak RSS). The
``cellcoadd`` command therefore keeps arrays up to 32 MB on the heap and keeps up to
256 MB of freed heap memory for the next ones. Results never depend on it. Settings
given in the environment (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``) win;
a program using the library from Python can set the same environment variables before it
starts. Dask workers get the same through
:data:`cellcoadd.execution.settings.DASK_WORKER_CONFIG` (the numbers have their one home there).
"""

from __future__ import annotations

from cellcoadd.execution.settings import apply_malloc_settings


def keep_freed_memory() -> bool:
    """Apply the settings above to this process (glibc only): whether they were applied.

    Nothing is done on other C libraries, or for a setting the environment already gives.
    """
    return apply_malloc_settings()
