"""numba's ``njit`` when numba is installed, otherwise a no-op decorator (same code, pure Python).

The model kernels are written as scalar loops in the subset of Python that numba compiles;
without numba they still run (slowly) and give the same results. Compiled code is cached in
``__pycache__`` (first use in a fresh checkout compiles for ~15 s). numba invalidates a cache
entry only when the file defining that function changes: after editing an inlined kernel in
``_cheb.py`` or ``_branches.py``, delete ``piezo_stage/model/__pycache__/*.nb*``.

For the type checker ``njit`` keeps the decorated function's signature: a numba dispatcher is
called like the Python function it compiles.
"""

from __future__ import annotations

from typing import Callable, TypeVar, cast, overload

_F = TypeVar("_F", bound=Callable[..., object])

try:  # pragma: no cover - exercised by whichever branch is installed
    import numba as _numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


def _compile(func: _F, inline: bool, nrt: bool) -> _F:
    """The numba dispatcher for ``func`` (see :func:`njit`), or ``func`` itself without numba."""
    if not HAVE_NUMBA:  # pragma: no cover
        # give the plain function ``py_func`` like a numba dispatcher
        func.py_func = func  # type: ignore[attr-defined]  # an attribute set on a function object
        return func
    options: dict[str, object] = dict(
        cache=True, nogil=True, error_model="numpy", inline="always" if inline else "never"
    )
    if not nrt:
        options["_nrt"] = False
    # numba's stubs list only its public options, not the private ``_nrt``: call it untyped
    compile_with = cast("Callable[..., Callable[[_F], object]]", _numba.njit)
    # a Dispatcher[_F] is called like _F
    return cast(_F, compile_with(**options)(func))


@overload
def njit(func: _F, *, inline: bool = False, nrt: bool = True) -> _F: ...
@overload
def njit(func: None = None, *, inline: bool = False, nrt: bool = True) -> Callable[[_F], _F]: ...
def njit(
    func: _F | None = None, *, inline: bool = False, nrt: bool = True
) -> _F | Callable[[_F], _F]:
    """Compile ``func`` in nopython mode, cached on disk, fast-math off (exact IEEE), with
    numpy's error model (x/0 gives inf or nan like numpy, no exception check per division).

    ``inline=True`` inlines the function into its callers (small hot kernels).
    ``nrt=False`` compiles without numba's runtime: no reference counting of the arrays it
    is given (an atomic operation per array per call, the largest cost of a small kernel
    called in a loop); the function must not allocate arrays.

    Without numba: return ``func`` unchanged and give it ``py_func`` like a numba dispatcher.
    """
    if func is None:
        return lambda f: _compile(f, inline, nrt)
    return _compile(func, inline, nrt)
