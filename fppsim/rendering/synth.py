"""One synthetic sample: seeded scene -> exact geometry -> fringe + PSP images -> PSP decode.

Every random draw of sample ``index`` comes from ``SeedSequence([seed, index, attempt])`` split into
independent streams (scene, optics, noise), so a sample depends only on the global seed, its global
index and the inputs: worker count, sharding and resumption do not change it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace as dc_replace

import numpy as np

from fppsim import __version__
from fppsim.errors import SampleError
from fppsim.rendering.optics import OpticsRanges, form_images, fringe_pixels, noise_source
from fppsim.rendering.render import DepthRenderer, scene_geometry
from fppsim.geometry.jitter import RigJitter, jitter_rig
from fppsim.geometry.rig import Rig
from fppsim.rendering.scene import MeshAsset, SceneRanges, sample_scene
from fppsim.phase.psp import decode_stacks
from fppsim.dataio.formats import psp_freq, psp_image_name

__all__ = ["SynthConfig", "SampleError", "synthesize", "psp_decode"]


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
                   supersample=int(d["supersample"]), psp_freqs=tuple(psp_freq(f) for f in d["psp_freqs"]), psp_steps=int(d["psp_steps"]),
                   min_object_fraction=float(d["min_object_fraction"]), max_attempts=int(d["max_attempts"]),
                   rig_jitter=RigJitter(**d.get("rig_jitter", {"yaw": 0.0, "focal": 0.0})))

    @classmethod
    def from_settings(cls, settings: dict) -> "SynthConfig":
        """The configuration a dataset was generated with, from its ``dataset.json``
        (:func:`fppsim.dataio.formats.read_settings`); KeyError/TypeError/ValueError when incomplete."""
        return cls.from_dict(settings["config"], Rig.from_dict(settings["rig"]))


def psp_decode(images: dict[int, list[np.ndarray]], rig: Rig, freqs: tuple[int, ...],
               min_modulation: float = 3.0) -> dict[str, np.ndarray]:
    """Decode PSP stacks ``{freq: [step images]}`` like a lab (:func:`fppsim.phase.psp.decode_stacks`).

    Returns float32 ``phase_psp`` (rad, absolute, highest frequency), ``height_psp`` (mm, NaN where
    rejected), ``mask_psp`` (1 where modulation suffices and the fringe order is reliable and consistent).
    """
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
        nothing is seen), phase_true (rad, projector phase of the single-shot frequency), mask (1 = seen,
        lit and not black: :func:`~fppsim.rendering.optics.fringe_pixels`), and with PSP phase_psp, height_psp,
        mask_psp.
    meta : everything needed to reproduce the sample.
    """
    k = config.supersample
    cam = config.rig.camera
    # Render a margin around the image so the optics' blurs see real scene content at the borders
    # (blurring with a clamped edge would shift the fringe phase of the outer columns); crop after.
    m = config.optics.render_margin()
    crop = (slice(m, m + cam.height), slice(m, m + cam.width))
    last_reason = ""
    for attempt in range(config.max_attempts):
        ss = np.random.SeedSequence([int(seed), int(index), attempt])
        # children keep their index: a child added at the end leaves the earlier draws as they were
        scene_ss, optics_ss, noise_ss, rig_ss, look_ss, pedestal_ss = ss.spawn(6)
        rig = jitter_rig(config.rig, np.random.default_rng(rig_ss), config.rig_jitter)
        render_rig = dc_replace(rig, camera=cam.expanded(m))
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
            names.append(psp_image_name(f, n))
    # the camera noise of the images, drawn on a helper thread while the images form
    noise_rng = None if noise_free else noise_source(np.random.default_rng(noise_ss), optics,
                                                     (cam.height + 2 * m, cam.width + 2 * m), len(patterns))
    imgs = form_images(geom_ss, rig, optics, patterns, noise_rng, k, np.random.default_rng(look_ss))
    images = {name: np.ascontiguousarray(img[crop]) for name, img in zip(names, imgs)}

    seen = geom.seen
    mask = fringe_pixels(geom, optics)  # lit, and not black: a black plane has no phase, hence no label
    arrays = {
        "height": np.where(seen, geom.points[..., 2], 0.0).astype(np.float32),
        "depth": np.where(seen, geom.depth, 0.0).astype(np.float32),
        "phase_true": np.where(seen, rig.phase_of_column(geom.u_p), 0.0).astype(np.float32),
        "mask": mask.astype(np.float32),
    }
    if config.psp_freqs:
        stacks = {f: [images[psp_image_name(f, n)] for n in range(config.psp_steps)] for f in config.psp_freqs}
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
            "shadow_fraction": float((seen & ~geom.lit).mean()),
            "max_height_mm": float(arrays["height"].max()),
            "intensity_p50": float(p50),
            "intensity_p99": float(p99),
        },
    }
    return images, arrays, meta
