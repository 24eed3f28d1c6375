"""Sim-to-real experiment: generate synthetic data -> train on it alone -> evaluate on REAL data -> report.

    from uhrnet.workflows.sim2real import Sim2RealConfig, Variant, run_sim2real

    run_sim2real(Sim2RealConfig(out="runs/s2r", real=["../shared/real-sample"],
                                variants=[Variant("default"), Variant("no-aug", train={"augment": "off"})]))

``uhrnet sim2real`` (and ``pipelines/sim2real.py``) calls the same. The judged recipe (``scale="cpu"``)
is exactly what these two commands do::

    fppsim generate --meshes ../shared/meshes assets/meshes --out syn --count 400 --seed 100 --workers 2 \
        --no-psp --format figshare
    uhrnet train --synthetic syn --model unet --base-channels 16 --loss compound --epochs 10 \
        --batch-size 2 --lr 5e-4 --device cpu --out run

followed by prediction on every real figshare-format pair (``f1_80.npy`` + ``Z.npy`` or the single
published ``fringe_pattern.npy`` + ``height_map.npy``) with the figshare label rule (label <= -100
invalid, mm = label / 6). ``scale="gpu"`` is the full recipe (UHRNet, 352 x 640, >= 2000 samples).

Variants (an ablation) change the dataset and/or the training run through overrides of
``GenerateConfig`` / ``TrainConfig`` fields (``train={"head": "phase"}``: the physics head); variants with
the same dataset overrides share one synthetic dataset. A variant may add rows without training again:
``adapt`` (``AdaptConfig`` overrides, ``{}`` for the defaults) fine-tunes its model on the UNLABELLED real
images (:mod:`uhrnet.training.adapt`; only fringe images are read), ``refine`` (``["relief", "orders"]``) measures
its predictions after ``--refine phase`` with each method; rows: the network, each refinement, the adapted
network and each refinement of it::

    Variant("phase-head", train={"head": "phase"}, adapt={"epochs": 20}, refine=["relief"])

``real_phase`` (real phase-shifting folders: ``PSin/ PCos/ Fringe/ iPattern/``) adds the calibration-free
phase residual of every row on every frame (``uhrnet evaluate-phase``'s metric). ``reuse={"name": RUN}``
takes a finished training run (same training options, dataset of ``count`` samples and ``seed``) instead of
training; a run folder copied to ``out/<name>/run`` is taken the same way. Every stage is resumable: a
finished dataset, a finished run (``last.pt`` at the requested epochs), a finished adaptation and a
finished evaluation are re-used.

Modules: :mod:`~uhrnet.workflows.sim2real.config` (:class:`Sim2RealConfig`, :data:`SCALES`, :class:`Variant`),
:mod:`~uhrnet.workflows.sim2real.variants` (the ``--variant SPEC`` / ``--ablation`` grammar -> :class:`Variant`),
:mod:`~uhrnet.workflows.sim2real.run` (the stages and :func:`run_sim2real`),
:mod:`~uhrnet.workflows.sim2real.score_real` (one checkpoint on the real pairs, the real phase frames and the
synthetic validation split),
:mod:`~uhrnet.workflows.sim2real.real_metrics` (object RMSE and its level / relief split, median error, coverage, fringe
twins, level response) and
:mod:`~uhrnet.workflows.sim2real.report` (``report.md``, figures).
"""

from uhrnet.errors import Sim2RealError
from uhrnet.workflows.sim2real.config import SCALES, Sim2RealConfig, Variant, data_key
from uhrnet.workflows.sim2real.real_metrics import (error_split, fringe_twins, level_response, object_mask, object_regions,
                                               plane_level, real_metrics, twin_metrics)
from uhrnet.workflows.sim2real.report import markdown_report, plot_real
from uhrnet.workflows.sim2real.score_real import (
    evaluate_level, evaluate_real, evaluate_real_phase, find_phase_frames, find_real_pairs, refine_labels,
)
from uhrnet.workflows.sim2real.run import adapt_config, generate_config, run_differences, run_sim2real, train_config

__all__ = [
    "Sim2RealConfig", "Variant", "Sim2RealError", "SCALES", "data_key", "object_mask", "plane_level", "real_metrics",
    "fringe_twins", "twin_metrics", "level_response", "generate_config", "train_config", "adapt_config",
    "run_differences", "find_real_pairs", "find_phase_frames", "refine_labels", "evaluate_real",
    "evaluate_real_phase", "evaluate_level", "run_sim2real", "markdown_report", "plot_real",
    "error_split", "object_regions",
]
