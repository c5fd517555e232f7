"""Fields that act only beside another field's value.

A spec's key is made from every field, so a field given a value where it cannot act changes
nothing but the key: the run is a second copy of one that may exist, under a new name, and the
person who wrote it believes they changed something. Such a field is refused by name (a spec
written out in full, as a store keeps it, carries these fields at their defaults, which passes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from esr_cli.model.spec import Spec


@dataclass(frozen=True)
class InertField:
    section: str  # the spec's section
    kind: str | None  # the section's kind it belongs to (None: a section without kinds)
    field: str
    needs: str  # the field of the same section that decides whether `field` acts
    acts_when: tuple[Any, ...]  # the values of `needs` under which it acts
    only_where: tuple[tuple[str, Any], ...] = ()  # (key path, value): the rule holds only where these do


INERT_FIELDS = (
    InertField("method", "esr", "inferred_codes", "human_action", ("inferred",)),
    InertField("method", "goal_inference", "step", "variant", ("original",)),
    InertField("human", "ppo", "kl_coef", "mode", ("bc_kl",)),
    InertField("human", "bc", "adapt_lr", "adapt", (True,)),
    InertField("human", "bc", "adapt_kl", "adapt", (True,)),
    InertField("human", "bc", "adapt_gamma", "adapt", (True,)),
    # the published Overcooked AvE steps once from s, whatever the rollout length (docs/baselines.md)
    InertField("method", "ave", "rollout_length", "variant", ("fixed",), only_where=(("env.kind", "overcooked"),)),
    InertField("network", None, "mlp_layers", "kind", ("mlp",)),
    InertField("network", None, "conv_channels", "kind", ("conv",)),
    InertField("network", None, "hidden", "kind", ("conv",)),
)


def as_yaml(value: Any) -> str:
    """A field's value as a spec file writes it."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(as_yaml(v) for v in value) + "]"
    return str(value)


def _value(spec: Spec, dotted: str) -> Any:
    node: Any = spec
    for part in dotted.split("."):
        node = getattr(node, part, None)
    return node


def first_inert(spec: Spec) -> tuple[str, str] | None:
    """(key path, problem) of the first field set away from its default where it cannot act."""
    for rule in INERT_FIELDS:
        section = getattr(spec, rule.section)
        if rule.kind is not None and getattr(section, "kind", None) != rule.kind:
            continue
        if any(_value(spec, path) != value for path, value in rule.only_where):
            continue
        value, default = getattr(section, rule.field), type(section).model_fields[rule.field].default
        decider = getattr(section, rule.needs)
        if value == default or decider in rule.acts_when:
            continue
        wanted = " or ".join(as_yaml(v) for v in rule.acts_when)
        where = "".join(f" and {path} is {as_yaml(v)}" for path, v in rule.only_where)
        return (f"{rule.section}.{rule.field}",
                f"{as_yaml(value)} does nothing while {rule.section}.{rule.needs} is {as_yaml(decider)}{where}; it "
                f"acts only with {rule.needs}: {wanted} (remove it, or set {rule.section}.{rule.needs}: {wanted})")
    return None
