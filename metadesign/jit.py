"""Compiled kernels (issue #35): numba's ``njit`` (compiled once, cached on disk, the GIL released) for the
two per-pillar kernels of a layout, the nearest-atom discretizer and the OASIS placement encoder.

Each compiled kernel has a numpy twin, the reference it is tested against: bit for bit for the layout's
kernels (the same index map, error sums and bytes) and the pillar look-up, to float32 rounding for the
coarse pupil's block sums (complex128 per block against the einsum's complex64: frames within ~3e-7).
Without numba (or a numba that does not import), or with ``METADESIGN_JIT=0`` in the environment, the numpy
path runs.  numba itself is imported when a kernel is first wanted (it takes 0.2 s and scipy with it:
``metadesign --help`` and the stages that need no kernel never pay it)."""

from __future__ import annotations

import importlib
import importlib.util
import os
import threading

__all__ = ["enabled", "njit", "compiled"]

_HAVE = importlib.util.find_spec("numba") is not None
_IMPORTS: list[bool] = []  # whether numba imports, tried once (when a kernel is first wanted)
_LOCK = threading.Lock()


def enabled() -> bool:
    """True when the compiled kernels run: numba imports and ``METADESIGN_JIT`` is not ``0``."""
    if not _HAVE or os.environ.get("METADESIGN_JIT", "1") == "0":
        return False
    if not _IMPORTS:
        try:
            importlib.import_module("numba")
            _IMPORTS.append(True)
        except Exception:  # e.g. a numba built for another numpy: the twins run
            _IMPORTS.append(False)
    return _IMPORTS[0]


class _Kernel:
    """A function to compile on its first call.  Compiling resolves the other kernels it calls through its
    module's globals, so every ``_Kernel`` there is replaced by its numba dispatcher first."""

    def __init__(self, fn, inline: bool):
        self.py_func, self.inline, self._dispatcher = fn, inline, None
        self.__name__, self.__doc__, self.__wrapped__ = fn.__name__, fn.__doc__, fn

    def dispatcher(self):
        with _LOCK:
            if self._dispatcher is None:
                numba = importlib.import_module("numba")
                # no fast-math: IEEE operations in the written order (the numpy twin's floats); numpy's error
                # model: no zero-division check per operation, which would keep loops from vectorising
                self._dispatcher = numba.njit(cache=True, nogil=True, error_model="numpy",
                                              inline="always" if self.inline else "never")(self.py_func)
            return self._dispatcher

    def __call__(self, *args):
        if self._dispatcher is None:  # first call: the module's kernels become dispatchers, once
            g = self.py_func.__globals__
            for name, v in list(g.items()):
                if isinstance(v, _Kernel):
                    g[name] = v.dispatcher()
        return self.dispatcher()(*args)


def njit(fn=None, *, inline: bool = False):
    """``fn`` compiled by numba on its first call (cached on disk beside its module, no GIL, no fast-math),
    or ``fn`` itself without numba.  ``inline``: a helper inlined into the kernels that call it (a call
    passing arrays costs tens of ns per cell)."""
    if fn is None:
        return lambda f: njit(f, inline=inline)
    return _Kernel(fn, inline) if _HAVE else fn


def compiled(kernel):
    """The numba dispatcher of a kernel (for a compiled loop of one's own that calls it, e.g. in a test):
    ``kernel`` itself when its module already swapped it in, or when it is a plain function."""
    return kernel.dispatcher() if isinstance(kernel, _Kernel) else kernel
