"""The workflow layer: experiments that compose BOTH packages (render with fppsim, train and evaluate
with uhrnet), above the library and below the commands.

    from uhrnet.workflows.sim2real import Sim2RealConfig, Variant, run_sim2real

Only the command layer reaches it (``uhrnet.cli``, ``pipelines/``, tests); no library module of fppsim or
uhrnet imports it, and it is the only part of uhrnet that may import fppsim's rendering modules
(``fppsim.generation`` ...; ``tests/test_layers.py`` checks both). Modules:

- :mod:`~uhrnet.workflows.stages`: what every workflow's stages share: a stage run with its output in a log
  (:func:`~uhrnet.workflows.stages.run_stage`), a figshare dataset's sample count, an experiment's YAML/JSON
  file; a run folder's history, finished epochs and the resume checks are :mod:`uhrnet.run_folder`'s.
- :mod:`~uhrnet.workflows.sim2real`: the sim-to-real experiment (``uhrnet sim2real``, ``pipelines/sim2real.py``,
  ``pipelines/scaling.py``), with its variant grammar (:mod:`~uhrnet.workflows.sim2real.variants`).
- :mod:`~uhrnet.workflows.scaling`: the scaling study's library (``pipelines/scaling.py``: arms x training seeds
  of sim2real): its arms file, a seed's folder and record, the study record ``scaling.json`` (add, merge,
  resume), its statistics, table and figures; the pipeline only parses its command line and launches the arms.
"""
