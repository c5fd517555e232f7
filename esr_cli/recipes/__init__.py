"""What each kind of artifact is made from and how: training runs and evaluations, exact
analyses, human data and humans (cloned or trained by PPO), suites and sweeps, and what a
command's target names. Each builds on the store's one lifecycle (esr_cli/storage/artifacts.py).
"""
