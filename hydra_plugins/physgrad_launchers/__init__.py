"""physgrad's Hydra launchers (physgrad.cluster): found by Hydra's plugin scan, used by physgrad's
commands in place of the launcher they extend."""
