"""The keyed code: everything that decides what a run computes.

The spec's models (spec.py), the training core (train.py: one jitted program per chunk of
epochs; learner.py: the soft-Q learner; replay.py; evaluate.py), networks, environments,
methods and human models. A run's key digests every file here (esr_cli/storage/provenance.py), so an
edit to any of them re-keys runs; nothing here imports from outside this package, and nothing
outside it changes a run's numbers. docs/architecture.md maps the paper's algorithm onto it.
"""
