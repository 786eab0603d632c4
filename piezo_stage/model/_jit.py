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

    def njit(func: Callable[..., Any] | None = None, *, inline: bool = False) -> Any:
        """Compile ``func`` in nopython mode, cached on disk, fast-math off (exact IEEE).

        ``inline=True`` inlines the function into its callers (small hot kernels).
        """
        options = dict(cache=True, nogil=True, inline="always" if inline else "never")
        if func is None:
            return lambda f: _numba.njit(**options)(f)
        return _numba.njit(**options)(func)

except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(func: Callable[..., Any] | None = None, *, inline: bool = False) -> Any:
        """Fallback: return ``func`` unchanged and give it ``py_func`` like a numba dispatcher."""

        def mark(f: Callable[..., Any]) -> Callable[..., Any]:
            f.py_func = f  # type: ignore[attr-defined]
            return f

        return mark if func is None else mark(func)
