"""Methods: what the robot is rewarded for, and any representation it learns.

Every method has the same small interface, so the one runner (esr_cli.model.train) drives
them all with the shared soft-Q learner:

    init(key, obs_example) -> state            (a pytree; () for methods that learn nothing)
    update(state, batch, key) -> (state, metrics)   one representation/model step
    reward(state, batch, key) -> float32[B]    the robot's reward for a critic batch
    updates_per_epoch: int                     how many `update` steps per epoch
    learns_policy: bool                        False: the robot acts uniformly at random
    metric_names: tuple[str, ...]              keys of `update`'s metrics
    all_metric_names (class attribute)         every key metric_names holds under any spec

A method with `acts_by_rule = True` (Goal Inference) instead decides every step itself:
    memory_init(obs) -> memory                 per environment, at an episode's start
    rule_step(memory, obs, prev_human_action, key) -> (action, memory)
    rule_metrics(memory, final_env_state) -> dict   end-of-episode metrics

Catalogue (docs/baselines.md): esr, random, ave, goal_inference, iq_learn, oracle. Build one
with `esr_cli.model.methods.registry.make_method`; a new one is added as registry.py says.
"""
