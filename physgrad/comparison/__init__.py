"""`physgrad compare` (its help: physgrad.comparison.study), by what changes together:
spec (settings, variants, budget), jobs (job files, launching, the study folder), calibration (the
calibrated clock), tuning (phase 1), evaluation (phase 2), summary (phase 3: verdicts, tables,
compare.md), figure (sensitivity.png) and study (the phases in turn, and the command)."""

from physgrad.comparison.calibration import calibrated_clock
from physgrad.comparison.evaluation import evaluation, evaluation_jobs
from physgrad.comparison.jobs import job_runs, job_yaml, launch
from physgrad.comparison.points import halton_points
from physgrad.comparison.search_space import learning_rate_key
from physgrad.comparison.spec import (
    PHASES,
    SETTINGS,
    StudySettings,
    Variant,
    build_variants,
    check_variants_build,
    parse_arguments,
    split_overrides,
    study_settings,
    variant_name,
)
from physgrad.comparison.study import Study, main, run_study
from physgrad.comparison.summary import analyse
from physgrad.comparison.tuning import tuning
from physgrad.timing import calibrate

__all__ = [
    "PHASES",
    "SETTINGS",
    "Study",
    "StudySettings",
    "Variant",
    "analyse",
    "build_variants",
    "calibrate",
    "calibrated_clock",
    "check_variants_build",
    "evaluation",
    "evaluation_jobs",
    "halton_points",
    "job_runs",
    "job_yaml",
    "launch",
    "learning_rate_key",
    "main",
    "parse_arguments",
    "run_study",
    "split_overrides",
    "study_settings",
    "tuning",
    "variant_name",
]
