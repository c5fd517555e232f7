"""Every environment, human model and method meets its interface (esr_cli/model/interfaces.py), with
each optional capability declared and backed by the members it promises."""

import pytest
from conftest import ROOT

from esr_cli.common import specs
from esr_cli.model import interfaces as api, spec as spec_model
from esr_cli.model.train import make_trainer

GRID_SPECS = ["grid_2", "grid_2_random", "grid_2_ave", "grid_2_goal_inference", "grid_2_iq_learn", "grid_2_oracle"]


@pytest.mark.parametrize("name", GRID_SPECS)
def test_every_gridworld_method_meets_its_interface(name):
    trainer = make_trainer(specs.load(ROOT / "experiments" / f"{name}.yaml", "smoke"))
    assert isinstance(trainer.env, api.Environment)
    assert isinstance(trainer.human, api.Human) and trainer.human.learns is False
    method = trainer.method
    assert isinstance(method, api.Method)
    assert all(isinstance(getattr(method, f), bool) for f in ("learns_policy", "acts_by_rule", "has_reward_table"))
    assert isinstance(method.updates_per_epoch, int) and isinstance(method.metric_names, tuple)
    if method.acts_by_rule:
        assert isinstance(method, api.RuleMethod)
    if method.has_reward_table:
        assert isinstance(method, api.TableMethod)


@pytest.mark.slow
def test_overcooked_environment_and_an_adapting_bc_human_meet_theirs():
    import jax
    import jax.numpy as jnp

    from esr_cli.model.envs import make_env
    from esr_cli.model.humans.bc import cloned_policy
    from esr_cli.model.humans.policy_human import PolicyHuman

    spec = specs.load(ROOT / "experiments/cramped_room.yaml", "smoke", ["human.adapt=true"])
    env = make_env(spec.env)
    assert isinstance(env, api.Environment)
    obs = env.observe(env.reset(jax.random.PRNGKey(0)))
    policy = cloned_policy(spec.human)
    params = policy.init(jax.random.PRNGKey(0), jnp.zeros(obs.shape))
    human = PolicyHuman(env=env, params=params, logits_fn=policy.logits, adapt=True)
    assert isinstance(human, api.LearningHuman) and human.learns is True and human.metric_names


def test_registry_builds_every_method_kind_of_the_spec():
    from esr_cli.model.methods.registry import METHODS, method_class

    assert set(METHODS) == set(spec_model.KIND_MODELS["method"])
    for kind in METHODS:
        assert hasattr(method_class(kind), "from_spec")
    with pytest.raises(ValueError, match="unknown method kind 'nope'"):
        method_class("nope")


def test_the_specs_static_facts_agree_with_the_code():
    """model/spec.py checks specs without importing JAX, so it keeps two facts of its own: which
    method kinds learn no policy, and each environment's robot action count."""
    from esr_cli.model.envs import make_env
    from esr_cli.model.methods.registry import METHODS

    assert spec_model.POLICY_FREE_METHODS == {k for k, cls in METHODS.items() if not cls._field_defaults["learns_policy"]}
    for name in ("grid_2", "cramped_room"):
        spec = specs.load(ROOT / "experiments" / f"{name}.yaml", "smoke", ["env.size=6"] if name == "grid_2" else [])
        assert spec.env.robot_actions == make_env(spec.env).num_robot_actions
