"""numba's ``njit`` when numba is installed, otherwise a no-op decorator (same code, pure Python).

The model kernels are written as scalar loops in the subset of Python that numba compiles;
without numba they still run (slowly) and give the same results. Compiled code is cached in
``__pycache__`` (first use in a fresh checkout compiles for ~15 s). numba invalidates a cache
entry only when the file defining that function changes: after editing an inlined kernel in
``_cheb.py`` or ``_branches.py``, delete ``piezo_stage/model/__pycache__/*.nb*``.
"""

from __future__ import annotations

from typing import Any, Callable

try:  # pragma: no cover - exercised by whichever branch is installed
    import numba as _numba

    HAVE_NUMBA = True

    def njit(
        func: Callable[..., Any] | None = None, *, inline: bool = False, nrt: bool = True
    ) -> Any:
        """Compile ``func`` in nopython mode, cached on disk, fast-math off (exact IEEE), with
        numpy's error model (x/0 gives inf or nan like numpy, no exception check per division).

        ``inline=True`` inlines the function into its callers (small hot kernels).
        ``nrt=False`` compiles without numba's runtime: no reference counting of the arrays it
        is given (an atomic operation per array per call, the largest cost of a small kernel
        called in a loop); the function must not allocate arrays.
        """
        options = dict(
            cache=True, nogil=True, error_model="numpy", inline="always" if inline else "never"
        )
        if not nrt:
            options["_nrt"] = False
        if func is None:
            return lambda f: _numba.njit(**options)(f)
        return _numba.njit(**options)(func)

except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(
        func: Callable[..., Any] | None = None, *, inline: bool = False, nrt: bool = True
    ) -> Any:
        """Fallback: return ``func`` unchanged and give it ``py_func`` like a numba dispatcher."""

        def mark(f: Callable[..., Any]) -> Callable[..., Any]:
            f.py_func = f  # type: ignore[attr-defined]
            return f

        return mark if func is None else mark(func)
