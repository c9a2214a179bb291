"""numba's ``njit`` for vbnav's compiled kernels (``motion_kernel``, ``line_vertical_kernel``), in one place.

``kernel`` compiles a function with ``nogil`` (a vision thread running it does not hold up the control loop)
and caches the machine code on disk, so a later start loads it instead of compiling again (7-8 s for the
vertical-line kernel on the project's VM). numba caches next to the source (``__pycache__``) or, where that
is not writable, in the user's cache folder (``NUMBA_CACHE_DIR`` or ``~/.cache/numba``). A user with
neither, such as a service account without a home running an installation it cannot write, makes
``njit(cache=True)`` raise at import, which stopped every ``vbnav`` command; there the kernels are compiled
without the disk cache: each start compiles them again (``warm_up`` does it before the first frame).

``AVAILABLE`` is False when numba does not import or ``VBNAV_NO_JIT`` is set; ``kernel`` is then the
identity and the callers use their numpy reference paths.
"""
from __future__ import annotations

import os

try:
    if os.environ.get("VBNAV_NO_JIT"):
        raise ImportError("VBNAV_NO_JIT is set")
    import numba

    AVAILABLE = True
except ImportError:
    numba = None
    AVAILABLE = False


def kernel(f):
    """``f`` compiled (nogil, disk-cached where a cache folder can be written), or ``f`` without numba."""
    if not AVAILABLE:
        return f
    try:
        return numba.njit(cache=True, nogil=True)(f)
    except RuntimeError:            # "cannot cache function ...: no locator available": compile at each start
        return numba.njit(nogil=True)(f)
