"""The scaling study of the sim-to-real recipe (``pipelines/scaling.py``, issue 32): arms x training seeds,
each (arm, seed) one :func:`~uhrnet.workflows.sim2real.run_sim2real` experiment; this package is the study's
library, the pipeline only parses its command line and launches the arms.

Modules: :mod:`~uhrnet.workflows.scaling.arms` (the arms file, an arm's label, folder, variant and steps),
:mod:`~uhrnet.workflows.scaling.results` (one (arm, seed) folder: its ``study.json`` and its results),
:mod:`~uhrnet.workflows.scaling.stats` (mean ± std over seeds, an arm against the reference arm, the samples
series' slope), :mod:`~uhrnet.workflows.scaling.report` (the table and figures) and
:mod:`~uhrnet.workflows.scaling.ledger` (the study record ``scaling.json``: read, add, merge, write).
"""

from uhrnet.workflows.scaling.arms import UsageProblem, arm_label, load_arms, steps_of
from uhrnet.workflows.scaling.ledger import load_ledger, merge_records, write_ledger
from uhrnet.workflows.scaling.results import seed_result
from uhrnet.workflows.scaling.stats import compare, series_slope, summarise

__all__ = ["UsageProblem", "arm_label", "load_arms", "steps_of", "load_ledger", "merge_records", "write_ledger",
           "seed_result", "compare", "series_slope", "summarise"]
