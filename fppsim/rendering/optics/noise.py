"""Camera noise: Gaussian read noise and shot noise, variance ``noise_sigma**2 + shot_noise * max(E, 0)``.

One float32 standard-normal draw of the image's shape per image, from ``ctx.noise_rng`` (None = a
noise-free image). :func:`noise_source` makes those draws ahead on a helper thread
(:class:`PrefetchedNormals`): the same arrays, in the same order.
"""

from __future__ import annotations

import queue
import threading

import numpy as np

from fppsim.rendering.optics.model import Effect, Param

__all__ = ["NOISE", "PrefetchedNormals", "noise_source"]


def _noise(E, optics, ctx):
    if ctx.noise_rng is None:
        return E
    sd = np.maximum(E, 0.0)
    sd *= optics.shot_noise
    sd += optics.noise_sigma ** 2
    np.sqrt(sd, out=sd)  # sqrt(noise_sigma**2 + shot_noise * max(E, 0))
    noise = ctx.noise_rng.standard_normal(E.shape, dtype=np.float32)
    if noise.dtype == sd.dtype:
        noise *= sd  # a fresh array: scaled in place, the same values as noise * sd
    else:
        noise = noise * sd  # (float64 images: the product in float64, as ever)
    E += noise
    return E


NOISE = Effect("camera noise", "sensor", (
    Param("noise_sigma", 1.0, (0.5, 1.5), "[0, inf)", off=0.0, unit="gray levels",
          doc="Gaussian read noise, gray levels."),
    Param("shot_noise", 0.05, (0.02, 0.08), "[0, inf)", off=0.0,
          doc="shot-noise variance per gray level of signal (gray levels)."),
), _noise)


class PrefetchedNormals:
    """The standard-normal draws of the camera noise, made ahead on a helper thread.

    Draws ``count`` float32 arrays of ``shape`` from ``rng`` in order, starting at once (numpy releases
    the GIL while it fills them), and hands them out through :meth:`standard_normal` in the same order:
    the very arrays ``rng.standard_normal(shape, dtype=np.float32)`` would have returned one call after
    another, so the images are unchanged; the image formation (blur, pattern lookups) of the main
    thread meanwhile runs on another core.
    """

    def __init__(self, rng: np.random.Generator, shape: tuple[int, int], count: int):
        self.shape, self.count = tuple(shape), int(count)
        self._ready: queue.SimpleQueue = queue.SimpleQueue()
        self._taken = 0
        self._thread = threading.Thread(target=self._draw, args=(rng,), name="fppsim-noise", daemon=True)
        self._thread.start()

    def _draw(self, rng) -> None:
        try:
            for _ in range(self.count):
                self._ready.put(rng.standard_normal(self.shape, dtype=np.float32))
        except BaseException as exc:  # handed to the caller's thread
            self._ready.put(exc)

    def standard_normal(self, size, dtype=np.float32) -> np.ndarray:
        if tuple(size) != self.shape or np.dtype(dtype) != np.float32 or self._taken >= self.count:
            raise RuntimeError(f"prefetched noise holds {self.count} float32 draws of {self.shape}; "
                               f"draw {self._taken + 1} asked for {np.dtype(dtype)} {tuple(size)}")
        self._taken += 1
        out = self._ready.get()
        if isinstance(out, BaseException):
            raise out
        return out


def noise_source(rng: np.random.Generator, optics, shape: tuple[int, int], count: int):
    """What the stage should draw the camera noise of ``count`` images of ``shape`` from: ``rng`` itself,
    or its draws made ahead (:class:`PrefetchedNormals`) when ``optics`` add noise."""
    if NOISE.is_on(optics):
        return PrefetchedNormals(rng, shape, count)
    return rng
