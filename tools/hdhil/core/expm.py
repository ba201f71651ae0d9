"""The matrix exponential of :func:`scipy.linalg.expm`, without importing scipy.linalg.

The plant's exact zero-order-hold discretisation (and the tracking design's) needs one
matrix exponential per step size, before the first cycle.  Importing :mod:`scipy.linalg`
for it costs more than all the rest of ``hdhil run``'s start-up: its array-API layer
clones the whole numpy namespace, which imports numpy.f2py, numpy.ma and numpy.testing.

:func:`expm` calls the compiled kernel that :func:`scipy.linalg.expm` calls
(``scipy.linalg._matfuncs_expm``: ``pick_pade_structure`` and ``pade_UV_calc``, the
scaling-and-squaring Padé algorithm of Al-Mohy and Higham, 2009), loaded on its own from
the installed scipy, and repeats the Python steps scipy's ``expm`` takes around it for
the one case it covers: a real float64 square matrix with entries both above and below
the diagonal (scipy's "generic" branch: Padé, then squaring by numpy's ``@``).  Same
kernel, same numpy operations in the same order: the result is bitwise scipy's
(``tests/test_expm.py`` checks it on every shipped scenario's plant).

Everything else goes to :func:`scipy.linalg.expm` itself: a scipy release whose
``expm`` wrapper differs (1.14 and older scale in Python, 1.18 moved the whole algorithm
to C; :data:`WRAPPER_RELEASES` lists the releases whose wrapper this repeats), a
triangular, diagonal, complex or batched input, a kernel error, a kernel not found.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import re
import sys
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["WRAPPER_RELEASES", "expm", "scipy_kernel"]

#: scipy releases (major, minor) whose ``scipy.linalg.expm`` is the wrapper repeated
#: here (identical code from 1.15.0 to 1.17.x).
WRAPPER_RELEASES = frozenset({(1, 15), (1, 16), (1, 17)})


_VERSION = re.compile(r"""^version\s*(?::\s*str\s*)?=\s*["']([^"']+)["']""", re.MULTILINE)


def _release(version: str) -> tuple[int, int] | None:
    parts = version.split(".")
    try:
        return int(parts[0]), int(parts[1])
    except (IndexError, ValueError):
        return None


@cache
def scipy_kernel() -> Any | None:
    """scipy's compiled expm kernel module, loaded without its package (which would
    import all of scipy.linalg), or None where this scipy's wrapper is not the one
    repeated here or the kernel is not where that wrapper finds it.  The release is read
    from the package's own ``version.py`` (what ``scipy.__version__`` imports), next to
    the kernel: no package metadata scan."""
    try:
        spec = importlib.util.find_spec("scipy")  # finds the package, does not import it
        if spec is None or not spec.submodule_search_locations:
            return None
        name = "scipy.linalg._matfuncs_expm"
        for folder in spec.submodule_search_locations:
            text = Path(folder, "version.py").read_text(encoding="utf-8")
            match = _VERSION.search(text)
            if match is None or _release(match.group(1)) not in WRAPPER_RELEASES:
                return None
            for suffix in importlib.machinery.EXTENSION_SUFFIXES:
                path = Path(folder, "linalg", "_matfuncs_expm" + suffix)
                if path.is_file():
                    loader = importlib.machinery.ExtensionFileLoader(name, str(path))
                    kspec = importlib.util.spec_from_file_location(name, path, loader=loader)
                    if kspec is None:
                        return None
                    # Left out of sys.modules (where a single-phase extension enters
                    # itself): no scipy.linalg submodule without scipy.linalg; that,
                    # imported later, loads its own from the library the interpreter
                    # keeps.
                    previous = sys.modules.get(name)
                    module = importlib.util.module_from_spec(kspec)
                    loader.exec_module(module)
                    if previous is not None:
                        sys.modules[name] = previous
                    elif sys.modules.get(name) is module:
                        del sys.modules[name]
                    return module
            return None
    except Exception:  # any surprise: scipy.linalg.expm does the work
        return None
    return None


def expm(a: np.ndarray) -> np.ndarray:
    """``scipy.linalg.expm(a)``, bitwise, without importing scipy.linalg where possible."""
    a = np.asarray(a)
    kernel = scipy_kernel() if _generic(a) else None
    if kernel is not None:
        # scipy.linalg._matfuncs.expm (1.15-1.17), the path of a 2-D float64 matrix
        # whose bandwidth is non-zero below and above the diagonal.
        n = a.shape[-1]
        e = np.empty(a.shape, dtype=a.dtype)
        am = np.empty((5, n, n), dtype=a.dtype)
        am[0, :, :] = a[()]
        m, s = kernel.pick_pade_structure(am)
        if m >= 0 and kernel.pade_UV_calc(am, m) == 0:
            ea = am[0]
            for _ in range(s):
                ea = ea @ ea
            e[()] = ea
            return e
    from scipy.linalg import expm as scipy_expm  # slow to import: only where needed

    return scipy_expm(a)  # type: ignore[no-any-return]


def _generic(a: np.ndarray) -> bool:
    """True for a float64 square matrix with a non-zero (or NaN) entry both below and
    above the diagonal: scipy's ``bandwidth(a)`` is then non-zero on both sides."""
    return (
        a.ndim == 2
        and a.shape[0] == a.shape[1] > 1
        and a.dtype == np.float64
        and bool(np.tril(a, -1).any())
        and bool(np.triu(a, 1).any())
    )
