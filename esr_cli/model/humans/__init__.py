"""Human models: the gridworld's noisy-greedy human (gridworld.py), the Overcooked humans cloned
from play (bc.py) or trained by PPO (ppo.py, conv_actor_critic.py), and what a run plays with
(registry.py: `make_human`, `policy_logits`).
"""
