"""submitit's SLURM launcher with a sweep's jobs ending one at a time
(physgrad.cluster.launch_array): `hydra/launcher=submitit_slurm` runs this one in physgrad's
commands, with the same settings (use_physgrad_launcher swaps it in before Hydra builds the
launcher). The plugin imports physgrad.cluster, never the other way round."""

from __future__ import annotations

from collections.abc import Sequence

from hydra.core.utils import JobReturn
from omegaconf import DictConfig, open_dict, read_write

try:
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import (
        SlurmLauncher as SubmititSlurmLauncher,
    )
except ImportError:  # without the launchers extra there is nothing to extend
    SubmititSlurmLauncher = None


SUBMITIT_SLURM = "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
PHYSGRAD_SLURM = "hydra_plugins.physgrad_launchers.slurm.SlurmLauncher"


class SlurmLauncher(SubmititSlurmLauncher or object):
    """Each job as a task of one SLURM job array, as submitit's launcher sends them; a job that
    ends without a result (cancelled, killed at its time limit, its node lost) is recorded and the
    others are waited for, and a stop of the sweep cancels the tasks still waiting."""

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        from physgrad.cluster import launch_array

        return launch_array(self, job_overrides, initial_job_idx)


def use_physgrad_launcher(config: DictConfig) -> None:
    """Before the sweep's launcher is built (Hydra's on_multirun_start): submitit's SLURM launcher
    replaced by physgrad's, its settings kept; any submitit launcher's folder made this launch's
    own (physgrad.cluster.own_submitit_folder)."""
    launcher = config.hydra.get("launcher")
    if launcher is not None and launcher.get("submitit_folder") is not None:
        from physgrad.cluster import own_submitit_folder

        folder = own_submitit_folder(str(launcher.submitit_folder))
        with read_write(launcher), open_dict(launcher):
            launcher.submitit_folder = folder
    if launcher is not None and launcher.get("_target_") == SUBMITIT_SLURM:
        from hydra.core.plugins import Plugins

        # Hydra's scan of hydra_plugins does not see a package installed in editable mode
        Plugins.instance().register(SlurmLauncher)
        with read_write(launcher), open_dict(launcher):
            launcher._target_ = PHYSGRAD_SLURM
