"""esr: experiments on assistive agents (Empowerment via Successor Representations)."""

__version__ = "0.1.0"
