"""Which class implements each `method.kind`. A new method is one file with a class that meets
`interfaces.Method` and has `from_spec(spec, env, human)`, one line here, and its spec model in
spec.py (docs/extending.md walks through it)."""

from __future__ import annotations

from importlib import import_module

# kind -> "module:Class"; modules are imported when their kind is used.
METHODS = {
    "esr": "esr_cli.methods.esr:ESR",
    "random": "esr_cli.methods.random:RandomRobot",
    "ave": "esr_cli.methods.ave:AvE",
    "goal_inference": "esr_cli.methods.goal_inference:GoalInference",
    "iq_learn": "esr_cli.methods.iq_learn:IQLearn",
    "oracle": "esr_cli.methods.oracle:Oracle",
}


def method_class(kind: str):
    if kind not in METHODS:
        raise ValueError(f"unknown method kind {kind!r}; known: {', '.join(METHODS)}")
    module, name = METHODS[kind].split(":")
    return getattr(import_module(module), name)


def make_method(spec, env, human=None):
    """The method of `spec.method.kind`, built from the spec, the environment and the human model."""
    return method_class(spec.method.kind).from_spec(spec, env, human)
