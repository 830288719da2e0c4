"""Saved policies: a trained agent's network parameters and the config that rebuilds its network, in one msgpack
file. No pickle: loading a file someone sent you runs no code, and a corrupt or mismatched file is refused.

A file is a msgpack map: `format` ("amjax-policy"), `version`, `agent` (a registered algorithm name), `config`
(JSON of every config field), `params` (the network's parameter tree as arrays) and `info` (JSON: e.g. the sweep's
config_id, best costed return and the env step it was reached at). A sweep writes one per configuration under
`policies/<config_id>.msgpack` (its best evaluation's policy); `save_policy` writes one from any params.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from amjax.agents.config import AgentConfig
from amjax.agents.registry import agent_of, algorithm
from amjax.agents.rollout import EnvBatch
from amjax.agents.training import Policy, evaluate_greedy
from amjax.files import atomic_write
from amjax.validation import check_real
from amjax.wrappers.active_measure import scaled_cost

FORMAT = "amjax-policy"
VERSION = 1


class PolicyFileError(ValueError):
    """A policy file that cannot be read, or whose contents do not fit the network its config describes."""


def params_template(agent: str, config: AgentConfig) -> Any:
    """Shapes and dtypes of the network parameters `config` builds (no arrays are allocated)."""
    algo = algorithm(agent)
    return jax.eval_shape(lambda key: algo.params(algo.init(config, algo.setup(config), key)), jax.random.key(0))


@dataclass(frozen=True)
class SavedPolicy:
    """A trained agent's greedy policy: `agent` name, its `config` and network `params` (+ free-form `info`)."""

    agent: str
    config: AgentConfig
    params: Any
    info: dict[str, Any] = field(default_factory=dict)

    def policy(self, num_envs: int = 1) -> Policy:
        """The greedy `(act, carry)` for a batch of `num_envs` envs (recurrent carries are sized to it)."""
        algo = algorithm(self.agent)
        return algo.greedy(self.config, algo.setup(self.config), self.params, int(num_envs))

    def evaluate(self, key: jax.Array, num_episodes: int = 10, **changes: Any) -> dict[str, float]:
        """Mean costed return, raw return, length and measurements over `num_episodes` greedy test episodes on
        the config's env; `changes` edit the config first (e.g. `cost=0.3` to score it at another cost). A
        cost-conditioned policy scored at `cost=c` plays episodes at cost c and sees c scaled by its training range
        (`cost_low`, `cost_high`), as in training."""
        draw = None
        if self.config.cost_conditioned and "cost" in changes:
            draw = float(check_real("cost", changes.pop("cost"), low=0.0))
        config = self.config.replace(**changes).validate() if changes else self.config
        means = _evaluate(self.agent, config, self.params, key, int(num_episodes), draw)
        return {name: float(value) for name, value in dataclasses.asdict(means).items()}

    def actor(self, seed: int = 0, cost: float | None = None) -> Actor:
        """A stateful one-env actor for NumPy loops (e.g. a Gymnasium env from `amjax.wrappers.gymnasium`); `seed`
        seeds the test policy's own draws (an actor-critic agent samples whether to measure). A cost-conditioned
        policy needs the `cost` the env charges: the actor appends it, scaled by the training range, to each
        observation (run it in an env at that fixed cost)."""
        return Actor(self, seed, cost)


@partial(jax.jit, static_argnames=("agent", "num_episodes"))
def _evaluate(agent: str, config: AgentConfig, params: Any, key: jax.Array, num_episodes: int, draw: Any = None):
    """`draw`: a cost-conditioned policy's test cost (the draw range (c, c), the scaling range kept)."""
    algo = algorithm(agent)
    setup = algo.setup(config)
    if draw is not None:
        setup = setup.replace(
            env_params=setup.env_params.replace(cost_low=jnp.float32(draw), cost_high=jnp.float32(draw))
        )
    return evaluate_greedy(algo, config, setup, params, key, num_episodes)


class Actor:
    """`actor(obs) -> action` for one env, step by step (an int for a Discrete env, a float32 NumPy array for a
    Box one); `reset()` at each episode start (recurrent agents start from a zero hidden state, as in training).
    Each call draws a fresh key for the test policy from `seed`'s stream."""

    def __init__(self, saved: SavedPolicy, seed: int = 0, cost: float | None = None):
        act, self._initial = saved.policy(num_envs=1)
        self._appended = np.zeros(0, np.float32)
        if saved.config.cost_conditioned:
            if cost is None:
                raise ValueError(
                    "cost: a cost-conditioned policy acts at a cost; allowed values: a number >= 0 "
                    "(e.g. actor(cost=0.2), in an env that charges 0.2)"
                )
            seen = scaled_cost(
                jnp.float32(check_real("cost", cost, low=0.0)),
                jnp.float32(saved.config.cost_low),
                jnp.float32(saved.config.cost_high),
            )
            self._appended = np.asarray(seen).reshape(1)
        elif cost is not None:
            raise ValueError(
                f"cost: got {cost!r} for a policy that is not cost-conditioned; allowed values: None "
                "(the env charges its own cost)"
            )

        def step(obs, carry, first, key):
            key, act_key = jax.random.split(key)
            action, carry, _ = act(EnvBatch(obs[None], None, first[None]), carry, act_key)
            return action[0], carry, key

        self._step = jax.jit(step)
        self._key = jax.random.key(seed)
        self.reset()

    def reset(self) -> None:
        self._carry, self._first = self._initial, True

    def __call__(self, obs: Any) -> int | np.ndarray:
        obs = np.asarray(obs, np.float32)
        if self._appended.size:  # a cost-conditioned policy's cost input
            obs = np.concatenate([obs, self._appended])
        action, self._carry, self._key = self._step(jnp.asarray(obs), self._carry, jnp.bool_(self._first), self._key)
        self._first = False
        return int(action) if action.ndim == 0 else np.asarray(action)


def save_policy(path: str | Path, config: AgentConfig, params: Any, info: dict[str, Any] | None = None) -> Path:
    """Write `params` of the agent that `config` configures to `path` (atomically); returns the path."""
    agent = agent_of(config)
    path = Path(path)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "agent": agent,
        "config": json.dumps(config.to_dict()),
        "params": serialization.to_state_dict(jax.tree.map(np.asarray, params)),
        "info": json.dumps(info or {}, default=float),
    }
    data = serialization.msgpack_serialize(payload)
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
    return path


def load_policy(path: str | Path) -> SavedPolicy:
    """Read a policy file; raise `PolicyFileError` (naming the file and the problem) if it is corrupt, from an
    unknown format or version, or if its parameters do not fit the network its config builds."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no policy file at {path}")
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise ValueError(f"not an {FORMAT} file")
        if payload.get("version") != VERSION:
            raise ValueError(f"version {payload.get('version')!r}; this amjax reads version {VERSION}")
        agent = payload["agent"]
        config = algorithm(agent).config_type.from_dict(json.loads(payload["config"]))
        info = json.loads(payload["info"])
        stored = payload["params"]
    except Exception as error:  # truncated bytes, wrong keys, bad JSON, unknown agent or field
        raise PolicyFileError(f"{path}: unreadable policy file ({error})") from None
    template = params_template(agent, config)
    try:
        params = serialization.from_state_dict(template, stored)
    except (ValueError, KeyError, TypeError) as error:
        raise PolicyFileError(f"{path}: parameters do not fit the {agent} network of its config ({error})") from None
    for (where, want), got in zip(jax.tree_util.tree_leaves_with_path(template), jax.tree.leaves(params), strict=True):
        got = np.asarray(got)
        if got.shape != want.shape or got.dtype != want.dtype:
            raise PolicyFileError(
                f"{path}: parameter {jax.tree_util.keystr(where)} has shape {got.shape} {got.dtype}, the {agent} "
                f"network of its config needs {want.shape} {want.dtype}"
            )
    return SavedPolicy(agent, config, jax.tree.map(jnp.asarray, params), info)


__all__ = [
    "Actor",
    "PolicyFileError",
    "SavedPolicy",
    "load_policy",
    "params_template",
    "save_policy",
]
