"""The spec's models: what an experiment is, as frozen pydantic models with their defaults,
ranges and cross-field rules. This is keyed code (esr_cli/model): a run's key digests these
defaults and rules beside the spec's values. Reading spec files (budgets, `extends:`, `--set`)
is esr_cli/common/specs.py. Nothing here imports JAX, so a bad spec is refused in a fraction of a second.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, Optional, Union, get_args

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, Strict, field_validator, model_validator

BUDGETS = ("paper", "quick", "smoke")

MAX_SEEDS = 1024
MAX_SEED = 2**31 - 1  # seeds become int32 PRNG keys
# Network sizes: far above any real run, low enough that the memory check sees the rest.
MAX_WIDTH, MAX_LAYERS = 1 << 14, 16
# Upper bounds on sizes that alone could hang or exhaust a machine; far above any real run.
MAX_EPOCHS, MAX_ENVS, MAX_UPDATES, MAX_ENV_STEPS = 10_000_000, 1 << 20, 1_000_000, 10**12
MAX_EVAL_EPISODES = 1_000_000  # eval.episodes, and `esr eval --episodes` that replaces it



def _why_text(value: str) -> str:
    """Why a number written as text was read as text: quotes around it, or a value that no
    setting takes (YAML reads `nan` and `inf` as words)."""
    try:
        number = float(value)
    except ValueError:
        return ""
    if number != number or number in (float("inf"), float("-inf")):
        return " (not a finite number)"
    return " (write it without quotes)"


def _a_number(what: str):
    """YAML's `true` and quoted text are not numbers, even where Python would convert them:
    `epochs: true` or `seeds: ["3"]` is a mistake to name, not a 1 or a 3 to guess."""

    def check(value):
        if isinstance(value, bool):
            raise ValueError(f"expected {what}, got the boolean {str(value).lower()}")
        if isinstance(value, str):
            raise ValueError(f"expected {what}, got the text {value[:40]!r}{_why_text(value)}")
        return value

    return BeforeValidator(check)


Int = Annotated[int, _a_number("an integer")]
Float = Annotated[float, _a_number("a number")]
Bool = Annotated[bool, Strict()]  # true/false only, not 1 or "yes"
Width = Annotated[int, _a_number("an integer"), Field(ge=1, le=MAX_WIDTH)]


def _widths(widths: tuple, what: str, allow_empty: bool) -> tuple:
    if not widths and not allow_empty:
        raise ValueError(f"needs at least one {what}")
    if len(widths) > MAX_LAYERS:
        raise ValueError(f"{len(widths)} {what}s: at most {MAX_LAYERS}")
    return widths


class _Model(BaseModel):
    # allow_inf_nan=False: `.inf` or `.nan` in any float field is refused by name
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# ---------------------------------------------------------------- environments
class GridworldEnvSpec(_Model):
    kind: Literal["gridworld"]
    size: Int = Field(5, ge=3, le=16, description="grid side length")
    blocks: Int = Field(2, ge=0, description="number of movable blocks")
    start: Literal["corner", "corner_hard", "center", "random"] = "corner"
    episode_steps: Int = Field(50, ge=1, le=10_000)
    goal_visible: Bool = Field(False, description="add a goal plane to the robot's observation (the Oracle)")

    @model_validator(mode="after")
    def _fits(self):
        cells = self.size * self.size
        # The human and the goal each need a cell free of blocks.
        if self.blocks > cells - 2:
            raise ValueError(
                f"blocks={self.blocks} does not fit a {self.size}x{self.size} grid: at most "
                f"{cells - 2} leave a cell for the human and one for the goal"
            )
        if self.start in ("corner", "corner_hard") and self.blocks < 2:
            raise ValueError(f"start={self.start!r} places two blocks beside the human: needs blocks >= 2")
        return self

    @property
    def robot_actions(self) -> int:
        """The robot's action count: a cell and one of five moves for whatever stands there
        (envs/gridworld.py; a test keeps the two equal)."""
        return self.size * self.size * 5


OVERCOOKED_LAYOUTS = ("cramped_room", "coord_ring", "asymm_advantages", "forced_coord", "counter_circuit")


class OvercookedEnvSpec(_Model):
    """JaxMARL's Overcooked: robot = agent_0, human = agent_1 (docs/overcooked.md)."""

    kind: Literal["overcooked"]
    layout: Literal[OVERCOOKED_LAYOUTS]
    episode_steps: Int = Field(400, ge=1, le=10_000)
    robot_seat: Annotated[Literal[0, 1], _a_number("0 or 1")] = Field(0, description="JaxMARL's agent the robot plays (1: the flipped seats; "
                                      "`esr eval --seat 1`)")

    @property
    def robot_actions(self) -> int:
        """Overcooked's six moves: four directions, stay, interact (envs/overcooked.py)."""
        return 6


EnvSpec = Annotated[Union[GridworldEnvSpec, OvercookedEnvSpec], Field(discriminator="kind")]


# ---------------------------------------------------------------- human models
class NoisyGreedyHumanSpec(_Model):
    kind: Literal["noisy_greedy"]
    noise: Float = Field(0.2, ge=0.0, le=1.0, description="probability of a uniformly random action")


MAX_PLAY_EPISODES = 10_000


def is_play_key_ref(text: str) -> bool:
    """A played episode's key (32 hex digits, lower case) or a prefix of at least 4 of them."""
    return 4 <= len(text) <= 32 and all(c in "0123456789abcdef" for c in text)


def not_a_play_key(text: str) -> str:
    return (f"{text[:40]!r} is not a play artifact's key (32 hex digits as `esr plays` lists them, "
            "or a unique prefix of at least 4)")


# Named humans per layout, each the fields of a human section (its kind included). Only the
# layouts the paper reports have one. paper_random: the MLP cloning settings whose human, with the
# Random robot, scores closest to the published Random column (quick budget, 3 seeds). paper: per
# layout, the candidate of `esr human calibrate` closest to that column by the selection rule
# (every candidate tried, and the rule, are in docs/overcooked.md).
_CLOSEST_CLONES = {
    "cramped_room": {"kind": "bc", "stay_weight": 0.05, "hidden": (64, 64), "epochs": 60},
    "coord_ring": {"kind": "bc", "stay_weight": 1.0, "hidden": (64, 64), "epochs": 60},
    "asymm_advantages": {"kind": "bc", "stay_weight": 0.1, "hidden": (128, 128), "epochs": 200},
}
HUMAN_PRESETS = {
    "paper_random": _CLOSEST_CLONES,
    "paper": {
        **_CLOSEST_CLONES,
        # the paper's network, trained by PPO beside a partner that acts at random half the time
        "cramped_room": {"kind": "ppo", "mode": "shaped", "total_steps": 1_000_000, "random_partner": 0.5},
    },
}


class BCHumanSpec(_Model):
    """Behavioural cloning on the 2019 human-human trials (or on played episodes, `data`); a
    stored artifact of kind humans
    (docs/overcooked.md). The cloning fields make the artifact's key; the adapt fields act
    only during training."""

    kind: Literal["bc"]
    layout: Optional[Literal[OVERCOOKED_LAYOUTS]] = Field(None, description="the data's layout; default: env.layout")
    network: Literal["mlp", "conv"] = Field(
        "mlp", description="mlp: tanh layers of widths `hidden`; conv: the paper's convolutional actor-critic "
        "(its policy tower; fixed shape, so `hidden` does not apply)",
    )
    hidden: tuple[Width, ...] = Field((64, 64), description="MLP widths (tanh, orthogonal init)")
    stay_weight: Float = Field(0.1, gt=0.0, le=1.0, description="cross-entropy weight of 'stay' samples")
    epochs: Int = Field(60, ge=1, le=1_000_000)
    lr: Float = Field(1e-3, gt=0.0)
    batch_size: Int = Field(256, ge=1, le=1 << 20)
    seed: Int = Field(0, ge=0, le=MAX_SEED)
    split: Literal["train", "test"] = Field(
        "train", description="which split of the human data to clone: test gives a held-out proxy human "
        "(`esr eval --human proxy`)",
    )
    selfplay_episodes: Int = Field(64, ge=2, le=100_000, description="BC+BC episodes for the recorded self-play return")
    data: Optional[tuple[str, ...]] = Field(
        None, description="clone from these played episodes (keys of `play` artifacts, `esr plays`) instead of the "
        "2019 trials; their last quarter is the test split",
    )
    preset: Optional[Literal[tuple(HUMAN_PRESETS)]] = Field(
        None, description="a named human for the layout, setting these fields and the kind (paper: the calibrated "
        "human closest to the paper's Random column; paper_random: the closest MLP clone; docs/overcooked.md)",
    )
    per_seed: Bool = Field(False, description="clone one human per training seed (cloning seed = human.seed + "
                           "the training seed), so that the seeds' spread includes the human's")
    adapt: Bool = Field(False, description="the human keeps learning alongside the robot")
    adapt_lr: Float = Field(1e-4, gt=0.0)
    adapt_kl: Float = Field(1.0, ge=0.0, description="weight of KL(pi_BC || pi) in the human's loss")
    adapt_gamma: Float = Field(0.99, ge=0.0, le=1.0, description="the human's discount for reward-to-go")

    @field_validator("hidden")
    @classmethod
    def _layers(cls, v):
        return _widths(v, "layer", allow_empty=False)

    @model_validator(mode="after")
    def _hidden_is_the_mlps(self):
        if self.network == "conv" and "hidden" in self.model_fields_set:
            raise ValueError("human.hidden sizes the MLP: network conv is the paper's network, of one fixed shape")
        return self

    @field_validator("data")
    @classmethod
    def _play_keys(cls, v):
        if v is None:
            return v
        if not v or len(v) > MAX_PLAY_EPISODES:
            raise ValueError(f"between 1 and {MAX_PLAY_EPISODES} played episodes")
        v = type(v)(k.lower() for k in v)  # a key is hex: ABC... and abc... name the same episode
        # A unique prefix (4 hex digits or more) is completed from the store by the command that
        # reads the spec (targets.complete_play_keys); only whole keys make a human's key.
        bad = [k for k in v if not is_play_key_ref(k)]
        if bad:
            raise ValueError(not_a_play_key(bad[0]))
        if len(set(v)) != len(v):
            raise ValueError("an episode is listed twice")
        return v

    def cloning_part(self, layout: str) -> dict:
        """The fields that decide the cloned policy (the human artifact's key)."""
        d = self.model_dump(mode="json")
        keep = ("hidden", "stay_weight", "epochs", "lr", "batch_size", "seed", "selfplay_episodes")
        part = {"layout": self.layout or layout, **{k: d[k] for k in keep}}
        if self.split != "train":  # only when set, so that the humans cloned before this field keep their keys
            part["split"] = self.split
        if self.network != "mlp":  # likewise
            part["network"] = self.network
            del part["hidden"]
        if self.data is not None:  # likewise
            part["data"] = list(self.data)
        return part

    def proxy(self) -> "BCHumanSpec":
        """The held-out proxy of this human: the same cloning (per seed if this one is), on the
        test split, not adapting."""
        return self.model_copy(update={"split": "test", "adapt": False})

    def clones(self, seeds: tuple[int, ...]) -> list["BCHumanSpec"]:
        """The cloned humans a run with these training seeds uses: one, or one per seed."""
        if not self.per_seed:
            return [self]
        return [self.model_copy(update={"seed": self.seed + s, "per_seed": False}) for s in seeds]


PPO_HUMAN_MODES = ("selfplay", "shaped", "bc_kl")


class PPOHumanSpec(_Model):
    """The paper's Overcooked human network (a convolutional actor-critic) trained by PPO in
    self-play; a stored, resumable artifact of kind humans (docs/overcooked.md). Every field
    but `chunk_updates` and `min_selfplay_return` makes the artifact's key."""

    kind: Literal["ppo"]
    layout: Optional[Literal[OVERCOOKED_LAYOUTS]] = Field(None, description="the layout it learns in; default: env.layout")
    mode: Literal[PPO_HUMAN_MODES] = Field(
        "shaped", description="selfplay: the sparse soup reward only; shaped: plus the shaped reward, annealed to 0 over "
        "the first half; bc_kl: the sparse reward plus kl_coef * KL(pi_clone || pi) towards the BC human `clone`",
    )
    total_steps: Int = Field(5_000_000, ge=1, le=10**10, description="environment steps of training")
    num_envs: Int = Field(16, ge=1, le=4096)
    rollout_steps: Int = Field(128, ge=1, le=100_000)
    lr: Float = Field(2.5e-4, gt=0.0, description="Adam's learning rate, annealed linearly to 0")
    ent_coef: Float = Field(0.01, ge=0.0)
    kl_coef: Float = Field(1.0, ge=0.0, description="mode bc_kl: the KL term's weight")
    random_partner: Float = Field(
        0.0, ge=0.0, le=1.0, description="probability that the partner's seat (the robot's) acts uniformly at random in "
        "a step instead of by the network; those steps are not learnt from (1: trained beside the paper's Random robot)",
    )
    clone: Optional[BCHumanSpec] = Field(None, description="mode bc_kl: the BC human it is pulled towards "
                                         "(default: kind bc with its defaults)")
    preset: Optional[Literal[tuple(HUMAN_PRESETS)]] = Field(
        None, description="a named human for the layout, setting these fields (docs/overcooked.md)")
    seed: Int = Field(0, ge=0, le=MAX_SEED)
    per_seed: Bool = Field(False, description="train one human per training seed (seed = human.seed + the training "
                           "seed), as the paper had one human per seed")
    eval_episodes: Int = Field(64, ge=2, le=100_000, description="episodes with each partner (random, stay, itself) "
                               "for the returns the artifact records")
    chunk_updates: Int = Field(25, ge=1, le=1_000_000, description="updates between checkpoints (not part of the key)")
    min_selfplay_return: Float = Field(1.0, ge=0.0, description="a trained human whose self-play return is below this "
                                       "is refused (0 accepts any; not part of the key)")

    @model_validator(mode="after")
    def _clone_only_for_bc_kl(self):
        if self.clone is not None and self.mode != "bc_kl":
            raise ValueError(f"human.clone is the policy of mode bc_kl; mode is {self.mode!r}")
        if self.clone is not None and (self.clone.adapt or self.clone.per_seed or self.clone.preset):
            raise ValueError("human.clone is one fixed BC human written out field by field: adapt, per_seed and "
                             "preset do not apply to it")
        return self

    def bc_clone(self) -> BCHumanSpec | None:
        """The BC human of mode bc_kl (None in the other modes)."""
        if self.mode != "bc_kl":
            return None
        return self.clone or BCHumanSpec(kind="bc", layout=self.layout)

    def training_part(self, layout: str) -> dict:
        """The fields that decide the trained policy (the artifact's key, beside the clone's key)."""
        d = self.model_dump(mode="json")
        keep = ("mode", "total_steps", "num_envs", "rollout_steps", "lr", "ent_coef", "seed", "eval_episodes")
        part = {"layout": self.layout or layout, **{k: d[k] for k in keep}}
        if self.mode == "bc_kl":
            part["kl_coef"] = d["kl_coef"]
        if self.random_partner:  # only when set, so that the humans trained before this field keep their keys
            part["random_partner"] = d["random_partner"]
        return part

    def clones(self, seeds: tuple[int, ...]) -> list["PPOHumanSpec"]:
        """The trained humans a run with these training seeds uses: one, or one per seed."""
        if not self.per_seed:
            return [self]
        return [self.model_copy(update={"seed": self.seed + s, "per_seed": False}) for s in seeds]


# The human kinds that are stored artifacts made from Overcooked (cloned or trained).
STORED_HUMAN_KINDS = ("bc", "ppo")

HumanSpec = Annotated[Union[NoisyGreedyHumanSpec, BCHumanSpec, PPOHumanSpec], Field(discriminator="kind")]


# ---------------------------------------------------------------- methods
class _MethodModel(_Model):
    """What shared code asks of any method's spec, so that the runner, the memory check and the
    spec's cross-checks never ask for a method's kind. The defaults: the method samples the
    replay buffer as the learner does, and adds nothing to memory or to the checks."""

    def replay_future_gamma(self, learner_gamma: float) -> float:
        """The discount of the future states the replay sampler draws for this method."""
        return learner_gamma

    def replay_episode_group(self) -> int:
        """Transitions drawn from each sampled episode in a representation batch."""
        return 1

    def reads_post_step_view(self) -> bool:
        """Whether every update reads the buffer as `replay.post_step_view` (o_{t+1} with a_t)."""
        return False

    def network_outputs(self) -> int:
        """Outputs of this method's own networks (0: none), for the memory estimate."""
        return 0

    def update_bytes(self, batch_size: int, obs_bytes: int) -> int:
        """Bytes one update holds beyond the networks' activations, per seed in flight."""
        return 0

    def table_bytes(self, buffer_size: int) -> int:
        """Bytes of tables over the whole replay buffer, per seed in flight."""
        return 0

    def check_with(self, spec: Spec) -> None:
        """Raise ValueError, naming the fields, where this method cannot run with the rest of `spec`."""


class ESRMethodSpec(_MethodModel):
    kind: Literal["esr"]
    repr_dim: Int = Field(32, ge=1, le=MAX_WIDTH)
    reward: Literal["dot", "simplified", "simplified_normalized"] = Field(
        "dot", description="dot: (phi - phi')^T psi(g); simplified: exp(|phi|^2 / 2d) (phi - phi')^T phi, "
        "no future state (the paper's appendix); simplified_normalized: (phi - phi')^T phi, the same with "
        "its partition function divided out (docs/estimators.md)",
    )
    infonce: Literal["stacked", "separate"] = "stacked"
    episode_group: Int = Field(
        1, ge=1, le=1 << 20,
        description="transitions drawn from each sampled episode in a representation batch: 1 (the paper) "
        "draws them independently; k > 1 gives every anchor k - 1 negatives from its own episode (docs/estimators.md)",
    )
    future: Literal["full", "human"] = Field(
        "full", description="what psi sees of the future state: all of it, or only the human's part (docs/estimators.md)"
    )
    human_action: Literal["observed", "inferred"] = Field(
        "observed", description="inferred: phi never reads the human's action; it gets the code of a latent-action "
        "model trained on observations alone (docs/estimators.md)",
    )
    inferred_codes: Int = Field(8, ge=2, le=64, description="human_action: inferred: the latent code's size")
    pairing: Literal["aligned", "original"] = Field(
        "aligned", description="original: every update pairs o_{t+1} with a_t, as the published Overcooked code "
        "(docs/choices.md); aligned: o_t with a_t, as the paper's equations",
    )
    action_input: Literal["broadcast", "append"] = Field(
        "broadcast", description="how actions enter phi: one-hot planes over the grid, or appended once to the "
        "flattened observation (the published Overcooked code; needs network.kind: mlp)",
    )
    condition_on_robot_action: Bool = True
    future_gamma: Float = Field(0.9, ge=0.0, lt=1.0, description="future-state horizon: K ~ Geom(1 - future_gamma)")
    repr_lr: Float = Field(1e-4, gt=0.0)
    repr_updates_per_epoch: Int = Field(100, ge=0, le=MAX_UPDATES)

    def replay_future_gamma(self, learner_gamma: float) -> float:
        return float(self.future_gamma)  # ESR's own future-state horizon

    def replay_episode_group(self) -> int:
        return int(self.episode_group)

    def reads_post_step_view(self) -> bool:
        return self.pairing == "original"

    def network_outputs(self) -> int:
        return self.repr_dim

    def update_bytes(self, batch_size: int, obs_bytes: int) -> int:
        return 16 * batch_size * batch_size  # the batch x batch InfoNCE logits, 4 float32 copies

    def table_bytes(self, buffer_size: int) -> int:
        return 4 * 3 * buffer_size * self.repr_dim  # phi, phi' and psi of every stored transition

    def check_with(self, spec: Spec) -> None:
        if self.pairing == "original" and spec.env.kind != "overcooked":
            raise ValueError("method.pairing=original is the published Overcooked code's pairing; its gridworld code "
                             "pairs o_t with a_t, which is pairing: aligned (docs/choices.md)")
        if self.action_input == "append" and spec.network.kind != "mlp":
            raise ValueError("method.action_input=append feeds the one-hot once to a network that flattens its "
                             "input: it needs network.kind: mlp (a convolution would see it in one cell only)")
        if self.episode_group > spec.learner.batch_size:
            raise ValueError(f"method.episode_group={self.episode_group} is larger than "
                             f"learner.batch_size={spec.learner.batch_size}: a batch cannot hold one group")


class RandomMethodSpec(_MethodModel):
    kind: Literal["random"]


class AvEMethodSpec(_MethodModel):
    """Assistance via Empowerment (Du et al. 2020): reward = log variance of the human's
    position after random human rollouts from the current state (docs/baselines.md)."""

    kind: Literal["ave"]
    num_rollouts: Int = Field(20, ge=2, le=10_000, description="M rollouts per state")
    rollout_length: Int = Field(5, ge=1, le=10_000, description="L random human actions per rollout")
    variant: Literal["fixed", "original"] = Field(
        "fixed", description="original: the published code's action sampling and features (docs/baselines.md)"
    )

    def update_bytes(self, batch_size: int, obs_bytes: int) -> int:
        return 2 * batch_size * self.num_rollouts * (self.rollout_length + 1) * obs_bytes  # the rollouts' observations


class GoalInferenceMethodSpec(_MethodModel):
    """Goal inference, then a rule that clears the human's way (docs/baselines.md): esr's exact
    Bayesian belief under the known human model, or Du et al.'s published step rule."""

    kind: Literal["goal_inference"]
    variant: Literal["exact", "original"] = Field(
        "exact", description="original: Du et al.'s step update and goal-mass vote (docs/baselines.md)"
    )
    step: Float = Field(0.5, gt=0.0, le=10.0, description="original: alpha; each move shifts a goal's weight by alpha / |G|")

    def check_with(self, spec: Spec) -> None:
        if spec.env.kind != "gridworld":
            raise ValueError("method.kind=goal_inference needs the gridworld's known human model (env.kind: gridworld)")


class IQLearnMethodSpec(_MethodModel):
    """Reward inference with IQ-Learn (Garg et al. 2021): a soft Q of the human fitted online
    from the human's transitions; the robot is rewarded with r = Q(s, aH) - gamma V(s')."""

    kind: Literal["iq_learn"]
    gamma: Float = Field(0.9, ge=0.0, lt=1.0, description="the human's discount in the inverse soft-Q objective")
    alpha: Float = Field(1.0, gt=0.0, description="the human's soft-max temperature: V = alpha logsumexp(Q / alpha)")
    chi2: Float = Field(0.5, ge=0.0, description="weight of the chi-squared regulariser on the recovered reward")
    lr: Float = Field(1e-4, gt=0.0)
    updates_per_epoch: Int = Field(100, ge=0, le=MAX_UPDATES)


class OracleMethodSpec(_MethodModel):
    """An upper bound: the robot sees the goal (env.goal_visible) and gets the human's reward."""

    kind: Literal["oracle"]

    def check_with(self, spec: Spec) -> None:
        if spec.env.kind != "gridworld":
            raise ValueError("method.kind=oracle is gridworld-only: in Overcooked the goal is the shared reward (docs/baselines.md)")
        if not getattr(spec.env, "goal_visible", False):
            raise ValueError("method.kind=oracle needs env.goal_visible: true (the oracle sees the goal)")


# Every method's spec model, once: the union below and KIND_MODELS derive from it, and
# methods/registry.py has the class of each kind (tests/model/test_interfaces.py checks they agree).
METHOD_SPECS = (ESRMethodSpec, RandomMethodSpec, AvEMethodSpec, GoalInferenceMethodSpec, IQLearnMethodSpec, OracleMethodSpec)


# Kinds whose robot has no learned policy (each class's `learns_policy` is False; a test keeps
# the two equal), so the learner's fields do not act on it.
POLICY_FREE_METHODS = frozenset({"random", "goal_inference"})


def _kind(model) -> str:
    return get_args(model.model_fields["kind"].annotation)[0]


MethodSpec = Annotated[Union[METHOD_SPECS], Field(discriminator="kind")]


# ---------------------------------------------------------------- shared parts
class NetworkSpec(_Model):
    kind: Literal["conv", "mlp"] = Field("conv", description="conv: the gridworld conv net; mlp: flattened input, tanh")
    mlp_layers: tuple[Width, ...] = Field((64, 64), description="MLP widths (kind mlp)")
    conv_channels: tuple[Width, ...] = Field((16, 32), description="3x3 SAME convolutions, SiLU")
    hidden: Int = Field(100, ge=1, le=MAX_WIDTH)

    @field_validator("mlp_layers", "conv_channels")
    @classmethod
    def _layers(cls, v):
        return _widths(v, "layer", allow_empty=True)  # none: a linear map of the flattened input


class LearnerSpec(_Model):
    gamma: Float = Field(0.9, ge=0.0, lt=1.0, description="critic discount")
    lr: Float = Field(1e-3, gt=0.0)
    tau: Float = Field(0.005, gt=0.0, le=1.0)
    target_entropy: Float = Field(0.6, ge=0.0)
    dual_lr: Float = Field(0.1, ge=0.0)
    dual: Literal["squared", "linear"] = Field(
        "squared", description="beta's dual step: squared (original) or linear (SAC-style, on log beta)"
    )
    initial_beta: Float = Field(1.0, ge=1e-3, le=100.0)
    updates_per_epoch: Int = Field(100, ge=0, le=MAX_UPDATES)
    dual_updates_per_epoch: Int = Field(100, ge=0, le=MAX_UPDATES)
    batch_size: Int = Field(256, ge=2, le=1 << 20)
    buffer_size: Int = Field(15_000, ge=1, le=10**12, description="transitions held in the replay buffer (memory is checked before a run)")
    warmup_epochs: Int = Field(
        0, ge=0, le=MAX_EPOCHS, description="epochs in which the robot acts uniformly at random while every update runs"
    )


class TrainSpec(_Model):
    epochs: Int = Field(10_000, ge=1, le=MAX_EPOCHS)
    num_envs: Int = Field(100, ge=1, le=MAX_ENVS)
    seeds: tuple[Int, ...] = Field((0, 1, 2, 3, 4), description="a list of seeds, or a count n meaning 0..n-1")
    chunk_epochs: Int = Field(50, ge=1, le=MAX_EPOCHS, description="epochs per compiled chunk (progress/checkpoint interval)")

    @field_validator("seeds", mode="before")
    @classmethod
    def _count_means_range(cls, v):
        if isinstance(v, bool):
            raise ValueError("expected a list of seeds or a count")
        if isinstance(v, int):
            if v < 1:
                raise ValueError("a seed count must be >= 1")
            if v > MAX_SEEDS:  # checked before the range is built: a huge count must not hang
                raise ValueError(f"{v:,} seeds: at most {MAX_SEEDS:,} in one run (split them over runs)")
            return tuple(range(v))
        if not isinstance(v, (list, tuple)):
            raise ValueError(f"expected a list of seeds or a count (an integer), got {v!r:.40}")
        if len(v) > MAX_SEEDS:
            raise ValueError(f"{len(v):,} seeds: at most {MAX_SEEDS:,} in one run (split them over runs)")
        return v

    @field_validator("seeds")
    @classmethod
    def _distinct(cls, v):
        if len(v) == 0:
            raise ValueError("at least one seed is needed")
        if len(set(v)) != len(v):
            raise ValueError("seeds must be distinct")
        if any(s < 0 or s > MAX_SEED for s in v):
            raise ValueError(f"seeds must be between 0 and {MAX_SEED:,}")
        return v


class EvalSpec(_Model):
    episodes: Int = Field(100, ge=1, le=MAX_EVAL_EPISODES, description="evaluation episodes per seed and policy")


class Spec(_Model):
    name: str = Field(..., min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")
    env: EnvSpec
    human: HumanSpec
    method: MethodSpec
    network: NetworkSpec = NetworkSpec()
    learner: LearnerSpec = LearnerSpec()
    train: TrainSpec = TrainSpec()
    eval: EvalSpec = EvalSpec()
    budgets: dict[str, dict[str, Any]] = Field(default_factory=dict)
    budget: Literal["paper", "quick", "smoke"] = "paper"

    @field_validator("budgets")
    @classmethod
    def _known_budgets(cls, v):
        for name in v:
            if name not in BUDGETS:
                raise ValueError(f"unknown budget {name!r}; known: {', '.join(BUDGETS)}")
        return v

    @model_validator(mode="before")
    @classmethod
    def _human_preset(cls, data):
        """A human's `preset` sets the layout's human fields, its kind included, before validation:
        `human: {preset: NAME}` alone is the whole human; fields written beside it are kept unless
        the preset sets them."""
        human = data.get("human") if isinstance(data, dict) else None
        if not isinstance(human, dict) or human.get("preset") not in HUMAN_PRESETS:
            return data  # no preset, or an unknown one: the field's own check names it
        name = human["preset"]
        env = data.get("env") if isinstance(data.get("env"), dict) else {}
        layout = human.get("layout") or env.get("layout")
        settings = HUMAN_PRESETS[name]
        if layout not in settings:
            raise ValueError(f"human.preset={name!r} is defined for {', '.join(settings)} (the layouts the "
                             f"paper reports a Random score for), not {layout!r}")
        chosen = settings[layout]
        if human.get("kind", chosen["kind"]) != chosen["kind"]:
            raise ValueError(f"human.preset={name!r} makes a {chosen['kind']} human on {layout}, not kind "
                             f"{human['kind']!r}: give the preset alone, human={{preset: {name}}}")
        if chosen["kind"] == "bc" and "hidden" in chosen and human.get("network", "mlp") != "mlp":
            raise ValueError(f"human.preset={name!r} names MLP settings on {layout}: it does not apply to network "
                             f"{human['network']!r}")
        return {**data, "human": {**human, **chosen}}

    @model_validator(mode="after")
    def _cross_checks(self):
        stored = self.human.kind in STORED_HUMAN_KINDS
        if stored and self.env.kind != "overcooked":
            raise ValueError(f"human.kind={self.human.kind} is made from Overcooked play: it needs env.kind: overcooked")
        if self.human.kind == "noisy_greedy" and self.env.kind != "gridworld":
            raise ValueError("human.kind=noisy_greedy walks to a gridworld goal: it needs env.kind: gridworld")
        if stored and self.human.per_seed and self.human.seed + max(self.train.seeds) > MAX_SEED:
            raise ValueError(f"human.per_seed makes each human with seed human.seed + training seed, which passes "
                             f"{MAX_SEED:,} for human.seed={self.human.seed} and seed {max(self.train.seeds)}")
        if self.human.kind == "bc" and self.human.per_seed and self.human.adapt:
            raise ValueError("human.per_seed with human.adapt is not supported: an adapting human's pull back "
                             "to its clone assumes one clone")
        if stored and self.human.layout not in (None, self.env.layout):
            raise ValueError(f"human.layout={self.human.layout!r} differs from env.layout={self.env.layout!r}")
        clone = self.human.bc_clone() if self.human.kind == "ppo" else None
        if clone is not None and clone.layout not in (None, self.env.layout):
            raise ValueError(f"human.clone.layout={clone.layout!r} differs from env.layout={self.env.layout!r}")
        self.method.check_with(self)
        self._entropy_target_reachable()
        steps = self.env.episode_steps
        total = self.train.epochs * self.train.num_envs * steps * len(self.train.seeds)
        if total > MAX_ENV_STEPS:
            raise ValueError(f"train.epochs x train.num_envs x env.episode_steps x seeds = {total:.3g} environment steps; "
                             f"at most {MAX_ENV_STEPS:.0e} in one run")
        if self.learner.buffer_size < self.train.num_envs * steps:
            raise ValueError(
                f"learner.buffer_size={self.learner.buffer_size} cannot hold one epoch "
                f"(train.num_envs * env.episode_steps = {self.train.num_envs * steps} transitions)"
            )
        return self

    def _entropy_target_reachable(self) -> None:
        # The dual step drives the policy's entropy toward the target; at or above ln |A| (the
        # uniform policy's entropy) no temperature reaches it and beta only runs into its clip.
        learner = self.learner
        steered = self.method.kind not in POLICY_FREE_METHODS and learner.dual_lr > 0 and learner.dual_updates_per_epoch > 0
        ceiling = math.log(self.env.robot_actions)
        if steered and learner.target_entropy >= ceiling:
            raise ValueError(
                f"learner.target_entropy={learner.target_entropy:g} nats cannot be reached: a uniform policy over "
                f"the robot's {self.env.robot_actions} actions has ln {self.env.robot_actions} = {ceiling:.3f} nats")

    def training_part(self) -> dict:
        """The fields that determine a training run (the artifact key's spec component)."""
        d = self.model_dump(mode="json")
        # A preset is a name for the values it sets: the run is keyed by the values, so the same
        # human written out field by field is the same run (and runs from before the field keep their keys).
        d["human"].pop("preset", None)
        return {k: d[k] for k in ("env", "human", "method", "network", "learner", "train")}


# The spec model of each kind, for the sections that have kinds.
KIND_MODELS = {
    "env": {"gridworld": GridworldEnvSpec, "overcooked": OvercookedEnvSpec},
    "human": {"noisy_greedy": NoisyGreedyHumanSpec, "bc": BCHumanSpec, "ppo": PPOHumanSpec},
    "method": {_kind(m): m for m in METHOD_SPECS},
}
