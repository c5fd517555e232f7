"""The host side of a run: the loop that calls the jitted core chunk by chunk, checkpoints and
resumes, stop requests and signals, and the event logs. Nothing here changes a run's numbers
(resuming is bit-identical), so none of it is keyed.
"""
