"""Shared pieces of methods that learn no model of their own (Random, AvE, Oracle, Goal
Inference): no state, no update. Assign them in a method's class body."""

from __future__ import annotations


def stateless_init(self, key, obs_example):
    return ()


def no_update(self, state, batch, key):
    return state, {}
