"""Compiled kernels with a numpy reference, one process-wide choice (issue 12, item 3).

Each per-tick recursion that is compiled (the swarm's window fits, and the stages' tick kernels)
is a ``Kernel``: a plain-numpy reference, always there and always correct, and a source that
numba compiles (``cache=True``: the first process compiles in seconds, later ones load the cache
next to the package). ``select`` makes the choice for every kernel at once:

* ``None`` (the default): compiled where numba imports and compiles, else the reference;
* ``"compiled"``: compiled or an error (tests, benchmarks);
* ``"numpy"``: the reference everywhere (to compare, or in a sandbox that forbids the writable
  executable memory a JIT needs: the daemon's ``estimator.kernels``, set by the shipped systemd
  unit).

Kernels agree with their reference to float tolerance (each has a property test).
"""

from __future__ import annotations

import hashlib
import logging
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Generic, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

log = logging.getLogger(__name__)

#: A choice still running after this long is compiling, not loading the cache (~1 s): say so.
NOTICE_AFTER_S = 3.0

#: ``compiled`` or ``numpy`` once chosen; ``unset`` before the first choice
MODE = "unset"
_choice: str | None = None
_REGISTRY: list[Kernel[Any]] = []


class Kernel(Generic[F]):
    """One compiled kernel and its reference; call ``impl`` (the implementation in use).

    ``warm`` calls a candidate once with small arguments of every type the kernel is used with,
    so that compiling happens at ``select``, not in the middle of a run. ``depends`` names the
    other source files whose compiled code the kernel embeds (kernels it calls): numba's cache
    follows the kernel's own file only, so the cache entry is named after their contents too.
    """

    def __init__(
        self, name: str, reference: F, source: Callable[..., Any], warm: Callable[[F], object],
        *, fastmath: bool = False, depends: tuple[str, ...] = (),
    ) -> None:  # fmt: skip
        self.name = name
        self.reference = reference
        self._source = source
        self._warm = warm
        self._fastmath = fastmath
        self._depends = depends
        self._compiled: F | None = None
        self._tried = False
        self.impl: F = reference
        self.kind = "numpy"
        _REGISTRY.append(self)
        if MODE != "unset":  # a module imported after the choice follows it
            self._resolve()

    def compiled(self) -> F | None:
        """The compiled kernel (compiled or loaded once per process), or None where numba is
        missing or cannot compile here."""
        if not self._tried:
            self._tried = True
            try:
                import numba  # noqa: PLC0415 (optional: the reference runs without it)

                cache = True
                if self._depends:  # a cache entry per version of the files it embeds
                    try:
                        data = b"".join(Path(f).read_bytes() for f in self._depends)
                    except OSError:  # not readable (a zipped install): compiled, not cached
                        cache, data = False, b""
                    digest = hashlib.sha1(data).hexdigest()[:16]
                    self._source.__qualname__ = f"{self._source.__name__}_{digest}"
                jitted = numba.njit(cache=cache, nogil=True, fastmath=self._fastmath)(self._source)
                fn = cast(F, jitted)
                self._warm(fn)
                self._compiled = fn
            except Exception as exc:  # any failure leaves the reference, which always works
                warnings.warn(
                    f"compiled kernel {self.name} unavailable ({exc!r}): numpy used", stacklevel=2
                )
        return self._compiled

    def _resolve(self) -> None:
        compiled = None if _choice == "numpy" else self.compiled()
        if _choice == "compiled" and compiled is None:
            raise RuntimeError(f"the compiled kernel {self.name} is not available here")
        self.impl = compiled if compiled is not None else self.reference
        self.kind = "compiled" if compiled is not None else "numpy"


def select(name: str | None = None) -> str:
    """Choose the implementation of every kernel (``compiled``, ``numpy``; None: compiled where
    it works) and compile them now; returns ``compiled`` only if every kernel is compiled."""
    global MODE, _choice  # noqa: PLW0603 (one process-wide choice)
    if name not in (None, "compiled", "numpy"):
        raise ValueError(f"kernels must be 'compiled' or 'numpy', not {name!r}")
    _choice = name
    notice = threading.Timer(NOTICE_AFTER_S, _compiling_notice)
    notice.daemon = True
    notice.start()
    try:
        for k in _REGISTRY:
            k._resolve()
    finally:
        notice.cancel()
    MODE = "compiled" if all(k.kind == "compiled" for k in _REGISTRY) else "numpy"
    return MODE


def _compiling_notice() -> None:
    log.info(
        "compiling the engine's kernels: once after an install or an upgrade (about a minute "
        "on a 2-core machine), then loaded from numba's cache in about a second"
    )


def ensure() -> str:
    """Select now if nothing is chosen yet (compile or load at start-up); the mode in use."""
    return MODE if MODE != "unset" else select()


def restore(mode: str) -> None:
    """Return to a mode read from ``MODE`` earlier (``unset`` selects the default)."""
    select(None if mode == "unset" else mode)
