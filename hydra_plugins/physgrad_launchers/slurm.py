"""submitit's SLURM launcher with a sweep's jobs ending one at a time
(physgrad.cluster.launch_array): `hydra/launcher=submitit_slurm` runs this one in physgrad's
commands, with the same settings."""

from __future__ import annotations

from collections.abc import Sequence

from hydra.core.utils import JobReturn

try:
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import (
        SlurmLauncher as SubmititSlurmLauncher,
    )
except ImportError:  # without the launchers extra there is nothing to extend
    SubmititSlurmLauncher = None


class SlurmLauncher(SubmititSlurmLauncher or object):
    """Each job as a task of one SLURM job array, as submitit's launcher sends them; a job that
    ends without a result (cancelled, killed at its time limit, its node lost) is recorded and the
    others are waited for, and a stop of the sweep cancels the tasks still waiting."""

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        from physgrad.cluster import launch_array

        return launch_array(self, job_overrides, initial_job_idx)
