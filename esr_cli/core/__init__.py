"""The shared training core: replay buffer, soft-Q learner, runner, evaluation."""
