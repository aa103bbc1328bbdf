#!/usr/bin/env bash
# Run a physgrad command on a GPU machine that has jax with CUDA but no package index (docs/benchmarks.md,
# "On a GPU"): the wheels physgrad needs beyond that machine's packages are built where an index is reachable,
#
#   pip wheel --no-deps -w .whl . && pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 -d .whl \
#       hydra-core==1.3.2 omegaconf==2.3.0 optuna==5.0.0 colorlog sqlalchemy alembic mako psgdax==0.1.1
#
# carried there in .whl/ (ignored by git), and installed here into a temporary folder ahead of the machine's
# own packages. Usage: experiments/on_gpu.sh python3 -m physgrad run task=ks ...; a script that imports its
# neighbours needs its folder named: PYTHONPATH=experiments experiments/on_gpu.sh python3 experiments/reproduce.py
set -euo pipefail
site=$(mktemp -d)
python3 -m pip install -q --no-index --no-deps --target "$site" .whl/*.whl
# no preallocation: jobs and the bench share the GPU one after another; safe path: physgrad from the wheel, not
# the working tree (whose conf/ is the package's physgrad.conf only once installed)
export PYTHONSAFEPATH=1 PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH} PATH=$site/bin:$PATH XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
exec "$@"
