"""Which class implements each `method.kind`. A new method is one file with a class that meets
`interfaces.Method` and has `from_spec(spec, env, human)`, one line here, and its spec model in
spec.py. The imports are plain module-level imports on purpose: the run key's code digest
follows imports from the runner (provenance.module_closure), so every method's source is in it.
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
