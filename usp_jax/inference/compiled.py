"""A jitted function whose compiled programs are bounded: one per input shape, the most recently
used kept. ``jax.jit`` keeps every shape's program for the life of the function, and a detector
fed photos of many sizes compiles one per padded size (about 7 MB and 2 s each for the paper
network on a CPU), never freed: 40 sizes took a process from 422 to 691 MB. Here each shape gets
a jit of its own, dropped with its program, jaxpr and lowering when ``MAX_PROGRAMS`` newer
shapes have been used since; a dropped shape that comes back compiles again (from JAX's
persistent cache where one is set).
"""

from __future__ import annotations

import collections
import functools
from collections.abc import Callable

import jax

#: Programs kept per detector: enough for a batch's few sizes, a pyramid's levels or a video's
#: frame size beside a photo's, far below the hundreds a folder of mixed photos would compile.
MAX_PROGRAMS = 8


class BoundedJit:
    """``jax.jit(function, static_argnames="top_n", **options)`` that keeps the programs of the
    ``limit`` shapes (of the array arguments after the first, with ``top_n``) used last."""

    def __init__(self, function: Callable, limit: int = MAX_PROGRAMS, **options):
        self._function = function
        self._options = dict(static_argnames="top_n", **options)
        self._limit = limit
        self._programs: collections.OrderedDict = collections.OrderedDict()
        self._reference = jax.jit(function, **self._options)  # for lower(): one, never called

    def __call__(self, variables, *arrays, top_n=None):
        key = (tuple((a.shape, str(a.dtype)) for a in arrays), top_n)
        program = self._programs.pop(key, None)
        if program is None:  # a new callable: JAX's caches of the dropped ones go with them
            program = jax.jit(functools.partial(self._function), **self._options)
        self._programs[key] = program
        while len(self._programs) > self._limit:
            self._programs.popitem(last=False)
        return program(variables, *arrays, top_n=top_n)

    def lower(self, *args, **kwargs):
        """``jax.jit(...).lower``: for ahead-of-time analysis (memory, FLOPs) of one shape."""
        return self._reference.lower(*args, **kwargs)

    def _cache_size(self) -> int:
        """Compiled programs held now, as ``jax.jit``'s own ``_cache_size``."""
        return sum(program._cache_size() for program in self._programs.values())
