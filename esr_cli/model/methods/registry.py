"""Which class implements each `method.kind`. A new method is one file with a class that meets
`interfaces.Method` and has `from_spec(spec, env, human)`, one line here, and its spec model in
model/spec.py (docs/extending.md). Every file of esr_cli/model is in a run's key, so a new
method's source is keyed wherever it is imported from.
"""

from __future__ import annotations

from esr_cli.model.methods.ave import AvE
from esr_cli.model.methods.esr import ESR
from esr_cli.model.methods.goal_inference import GoalInference
from esr_cli.model.methods.iq_learn import IQLearn
from esr_cli.model.methods.oracle import Oracle
from esr_cli.model.methods.random import RandomRobot

METHODS = {
    "esr": ESR,
    "random": RandomRobot,
    "ave": AvE,
    "goal_inference": GoalInference,
    "iq_learn": IQLearn,
    "oracle": Oracle,
}


def method_class(kind: str):
    if kind not in METHODS:
        raise ValueError(f"unknown method kind {kind!r}; known: {', '.join(METHODS)}")
    return METHODS[kind]


def make_method(spec, env, human=None):
    """The method of `spec.method.kind`, built from the spec, the environment and the human model."""
    return method_class(spec.method.kind).from_spec(spec, env, human)
