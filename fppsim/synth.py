"""One synthetic sample: seeded scene -> exact geometry -> fringe + PSP images -> PSP decode.

Every random draw of sample ``index`` comes from ``SeedSequence([seed, index, attempt])`` split into
independent streams (scene, optics, noise), so a sample depends only on the global seed, its global
index and the inputs: worker count, sharding and resumption do not change it.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, field

import numpy as np

from . import __version__
from .errors import SampleError
from .optics import OVERSAMPLE, Optics, OpticsRanges, form_image, pattern_profile
from .render import DepthRenderer, Geometry, scene_geometry
from .jitter import RigJitter, jitter_rig
from .rig import Rig
from .scene import MeshAsset, SceneRanges, sample_scene

__all__ = ["SynthConfig", "SampleError", "synthesize", "render_images", "psp_decode"]


@dataclass
class SynthConfig:
    """Everything that defines a dataset besides the meshes and the seed.

    supersample : odd k; intensities are averaged over k x k sub-pixels, ground truth at pixel centres.
    psp_freqs : frequency ladder (periods across the projector) for the phase-shifting images; its
        last entry should be ``rig.periods``. Empty disables PSP.
    min_object_fraction : a scene whose objects cover less of the image than this is redrawn.
    """

    rig: Rig
    optics: OpticsRanges = field(default_factory=OpticsRanges)
    scene: SceneRanges = field(default_factory=SceneRanges)
    supersample: int = 1
    psp_freqs: tuple[int, ...] = (1, 8, 80)
    psp_steps: int = 4
    min_object_fraction: float = 0.02
    max_attempts: int = 8
    rig_jitter: RigJitter = field(default_factory=lambda: RigJitter(0.0, 0.0))  # opt-in

    def to_dict(self) -> dict:
        return {
            "optics_ranges": self.optics.to_dict(),
            "scene_ranges": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.scene).items()},
            "supersample": self.supersample,
            "psp_freqs": list(self.psp_freqs),
            "psp_steps": self.psp_steps,
            "min_object_fraction": self.min_object_fraction,
            "max_attempts": self.max_attempts,
            "rig_jitter": self.rig_jitter.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict, rig: Rig) -> "SynthConfig":
        """Inverse of :meth:`to_dict` (the rig is stored beside it, see :meth:`from_settings`)."""
        scene = {k: tuple(v) if isinstance(v, list) else v for k, v in d["scene_ranges"].items()}
        return cls(rig=rig, optics=OpticsRanges.from_dict(d["optics_ranges"]), scene=SceneRanges(**scene),
                   supersample=int(d["supersample"]), psp_freqs=tuple(d["psp_freqs"]), psp_steps=int(d["psp_steps"]),
                   min_object_fraction=float(d["min_object_fraction"]), max_attempts=int(d["max_attempts"]),
                   rig_jitter=RigJitter(**d.get("rig_jitter", {"yaw": 0.0, "focal": 0.0})))

    @classmethod
    def from_settings(cls, settings: dict) -> "SynthConfig":
        """The configuration a dataset was generated with, from its ``dataset.json``
        (:func:`fppsim.formats.read_settings`); KeyError/TypeError/ValueError when incomplete."""
        return cls.from_dict(settings["config"], Rig.from_dict(settings["rig"]))


def _irradiance_parts(geom: Geometry, optics: Optics) -> tuple[np.ndarray, np.ndarray]:
    albedo = np.where(geom.on_object, optics.albedo_object, optics.albedo_plane)
    seen = geom.seen
    base = np.where(seen, optics.gain * albedo * optics.ambient, 0.0)
    modulated = np.where(geom.lit, optics.gain * albedo * geom.cos_incidence * geom.falloff, 0.0)
    return base, modulated


def render_images(geom: Geometry, rig: Rig, optics: Optics, patterns: list[tuple[float, float]],
                  noise_rng: np.random.Generator | None, scale: int = 1,
                  appearance_rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """uint8 camera images for ``patterns`` = [(periods, phase shift rad), ...] on one geometry.

    Each image gets its own noise realisation from ``noise_rng`` (None = noise-free); the appearance
    effects of ``optics`` (texture, dirt, ...; :mod:`fppsim.appearance`) draw from ``appearance_rng``.
    """
    parts = tuple(a.astype(np.float32) for a in _irradiance_parts(geom, optics))
    parts = _appearance(parts, geom, rig, optics, appearance_rng, scale)
    # Linear interpolation weights into the oversampled 1-D pattern profile, shared by all patterns.
    x = (np.where(geom.lit, geom.u_p, 0.0) + 0.5) * OVERSAMPLE - 0.5
    n = rig.projector.width * OVERSAMPLE
    i0 = np.clip(np.floor(x), 0, n - 2).astype(np.intp)
    w = np.clip(x - i0, 0.0, 1.0).astype(np.float32)
    out = []
    for periods, shift in patterns:
        prof = pattern_profile(rig.projector.width, periods, shift, optics)[1].astype(np.float32)
        # prof[i0] + w * (prof[i0 + 1] - prof[i0]), the differences taken once on the profile (the same
        # float32 values) instead of per pixel; np.take: faster than fancy indexing
        pattern = np.diff(prof).take(i0)
        pattern *= w
        pattern += prof.take(i0)
        if getattr(optics, "subsurface", 0.0) > 0:
            from .appearance import subsurface_pattern

            pattern = subsurface_pattern(pattern, geom.on_object, optics.subsurface * scale)
        out.append(form_image(parts, pattern, optics, noise_rng, scale))
    return out


class PrefetchedNormals:
    """The standard-normal draws of :func:`fppsim.optics.form_image`, made ahead on a helper thread.

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


def _noise_source(rng: np.random.Generator, optics: Optics, shape: tuple[int, int], count: int):
    """What :func:`render_images` draws its camera noise from: ``rng`` itself, or its draws made ahead
    (:class:`PrefetchedNormals`) when the optics add noise to the ``count`` images of ``shape``."""
    if optics.noise_sigma > 0 or optics.shot_noise > 0:
        return PrefetchedNormals(rng, shape, count)
    return rng


def _appearance(parts, geom, rig, optics, rng, scale):
    """Texture, dirt, specular and vignetting (fppsim.appearance) when any is on; else ``parts``."""
    if not any(getattr(optics, k, 0.0) > 0 for k in ("albedo_texture", "dirt", "specular", "vignetting")):
        return parts
    from .appearance import apply_appearance

    return apply_appearance(parts, geom, rig, optics, rng if rng is not None else np.random.default_rng(0), scale)


def psp_decode(images: dict[int, list[np.ndarray]], rig: Rig, freqs: tuple[int, ...],
               min_modulation: float = 3.0) -> dict[str, np.ndarray]:
    """Decode PSP stacks ``{freq: [step images]}`` like a lab (:func:`fppsim.psp.decode_stacks`).

    Returns float32 ``phase_psp`` (rad, absolute, highest frequency), ``height_psp`` (mm, NaN where
    rejected), ``mask_psp`` (1 where modulation suffices and the fringe order is reliable and consistent).
    """
    from .psp import decode_stacks

    # on two threads (the same arrays): nothing else runs beside the decode
    d = decode_stacks({f: np.stack(images[f]) for f in freqs}, rig, freqs, min_modulation=min_modulation, threads=2)
    return {
        "phase_psp": d.phase.astype(np.float32),
        "height_psp": d.height.astype(np.float32),
        "mask_psp": d.valid.astype(np.float32),
    }


def synthesize(index: int, seed: int, assets: list[MeshAsset], config: SynthConfig,
               renderer: DepthRenderer, noise_free: bool = False) -> tuple[dict, dict, dict]:
    """Produce sample ``index``: ``(images, arrays, meta)``.

    images : {"fringe.png": uint8 (H, W), "psp/f{f}_s{n}.png": ...}
    arrays : float32 height (mm, world z; 0 where nothing is seen), depth (mm camera z-depth; 0 where
        nothing is seen), phase_true (rad, projector phase of the single-shot frequency), mask (1 = seen
        and lit), and with PSP phase_psp, height_psp, mask_psp.
    meta : everything needed to reproduce the sample.
    """
    k = config.supersample
    cam = config.rig.camera
    # Render a margin around the image so the camera blur sees real scene content at the borders
    # (blurring with a clamped edge would shift the fringe phase of the outer columns); crop after.
    m = int(np.ceil(4.0 * config.optics.camera_blur[1]))
    crop = (slice(m, m + cam.height), slice(m, m + cam.width))
    last_reason = ""
    for attempt in range(config.max_attempts):
        ss = np.random.SeedSequence([int(seed), int(index), attempt])
        # children keep their index: a child added at the end leaves the earlier draws as they were
        scene_ss, optics_ss, noise_ss, rig_ss, look_ss, pedestal_ss = ss.spawn(6)
        rig = jitter_rig(config.rig, np.random.default_rng(rig_ss), config.rig_jitter)
        render_rig = Rig(camera=cam.expanded(m), projector=rig.projector, periods=rig.periods, name=rig.name)
        scene = sample_scene(assets, rig, np.random.default_rng(scene_ss), config.scene,
                             pedestal_rng=np.random.default_rng(pedestal_ss))
        geom_ss = scene_geometry(render_rig, [o.instance() for o in scene.objects], renderer, scale=k)
        geom = geom_ss.at_pixel_centres(k).cropped(*crop)
        frac = float(geom.on_object.mean())
        if frac >= config.min_object_fraction:
            break
        last_reason = f"objects cover {100 * frac:.2f}% of the image (< {100 * config.min_object_fraction:.1f}%)"
    else:
        raise SampleError(f"sample {index}: nothing usable in view after {config.max_attempts} scene draws ({last_reason})")

    optics = config.optics.sample(np.random.default_rng(optics_ss))
    if noise_free:
        optics = optics.noise_free()
    patterns = [(float(rig.periods), 0.0)]
    names = ["fringe.png"]
    for f in config.psp_freqs:
        for n in range(config.psp_steps):
            patterns.append((float(f), 2.0 * np.pi * n / config.psp_steps))
            names.append(f"psp/f{f}_s{n}.png")
    # the camera noise of the images, drawn on a helper thread while the images form
    noise_rng = None if noise_free else _noise_source(np.random.default_rng(noise_ss), optics,
                                                      (cam.height + 2 * m, cam.width + 2 * m), len(patterns))
    imgs = render_images(geom_ss, rig, optics, patterns, noise_rng, k, np.random.default_rng(look_ss))
    images = {name: np.ascontiguousarray(img[crop]) for name, img in zip(names, imgs)}

    seen = geom.seen
    mask = geom.lit
    arrays = {
        "height": np.where(seen, geom.points[..., 2], 0.0).astype(np.float32),
        "depth": np.where(seen, geom.depth, 0.0).astype(np.float32),
        "phase_true": np.where(seen, rig.phase_of_column(geom.u_p), 0.0).astype(np.float32),
        "mask": mask.astype(np.float32),
    }
    if config.psp_freqs:
        stacks = {f: [images[f"psp/f{f}_s{n}.png"] for n in range(config.psp_steps)] for f in config.psp_freqs}
        arrays.update(psp_decode(stacks, rig, tuple(config.psp_freqs)))

    fringe = images["fringe.png"]
    # one partition for both, of the sorted image rebuilt from its histogram (the same values)
    p50, p99 = np.percentile(np.repeat(np.arange(256, dtype=np.uint8), np.bincount(fringe.ravel(), minlength=256)),
                             [50, 99]) if fringe.dtype == np.uint8 else np.percentile(fringe, [50, 99])
    meta = {
        "version": __version__,
        "index": int(index),
        "seed": int(seed),
        "attempt": attempt,
        "rig": rig.to_dict(),
        "layout": scene.layout,
        "objects": [o.to_dict() for o in scene.objects],
        "optics": optics.to_dict(),
        "noise_free": bool(noise_free),
        "supersample": k,
        "render_margin_px": m,
        "psp": {"freqs": list(config.psp_freqs), "steps": config.psp_steps,
                "shifts_rad": [2.0 * np.pi * n / config.psp_steps for n in range(config.psp_steps)]}
        if config.psp_freqs else None,
        "image_size": [cam.width, cam.height],
        "units": {"height": "mm (world z above the reference plane)", "depth": "mm (camera z-depth)",
                  "phase": "rad (2*pi*f*u_p/W_p)", "pose": "4x4, file coordinates times scale -> world mm"},
        "stats": {
            "object_fraction": frac,
            "valid_fraction": float(mask.mean()),
            "shadow_fraction": float((seen & ~mask).mean()),
            "max_height_mm": float(arrays["height"].max()),
            "intensity_p50": float(p50),
            "intensity_p99": float(p99),
        },
    }
    return images, arrays, meta
