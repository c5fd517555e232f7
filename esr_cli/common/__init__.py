"""Small modules every layer above the model uses: failures and their exit codes, bounded
readers of untrusted files (JSON lines, YAML, tar), spec-file reading, statistics, plotting
helpers, console printing and test fault points. They import only the model and each other.
"""
