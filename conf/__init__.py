"""physgrad's Hydra configs, installed as the package physgrad.conf (see pyproject.toml)."""
